"""Do two terms of the official D-3DGS code's deformation explain why it ends with fewer Gaussians?

    python benchmarks/official_terms.py --scene /tmp/mutant --term scale --steps 15000 \
        --output benchmarks/results/official_terms_mutant_scale_H100.json

Our `deform-splatfacto` ends 40k steps with more Gaussians than the official code on the same scene copies
(mutant 196,462 against 168,974; standup 84,504 against 83,149; benchmarks/HISTORY.md), and each code's count
repeats within about 1% from run to run. Reading both codes term by term (issue #33 item 3) found densification
and pruning equivalent, and two terms of how the deformation is applied that differ:

  scale     the official code adds the field's scale offset to the activated scale (exp(log s) + ds); ours adds
            it to the log-scale (exp(log s + ds)), which keeps scales positive.
  rotation  the official code hands q + dq to its rasterizer without normalising it, and the rasterizer builds
            the rotation matrix of that unnormalised quaternion (a rotation scaled by |q|^2 plus (1 - |q|^2) I:
            a change of shape as well); gsplat normalises every quaternion.

Each run trains `deform-splatfacto` with the named terms (`none`, `scale`, `rotation` or `scale+rotation`)
switched to the official code's way, in this process only (nothing in the plugin changes), and records the
number of Gaussians every `--every` steps. Densification ends at 15k, so the count at 15k is its final one;
run the terms in parallel processes on one GPU. `rotation` renders through gsplat with covariances: CUDA only.
`--score test` also scores the test split at the end with the term in place (none and scale: evaluation renders
normalised quaternions), so a 40k run of the scale term can be set against the official code's PSNR. Each frame is
then composed as in training (`score_with_term`); `--rescore RUN/nerfstudio_models` scores a finished run's
checkpoint again, on any device, into its result file:

    python benchmarks/official_terms.py --rescore runs/official_terms/scale/deform-splatfacto/nerfstudio_models \
        --scene /tmp/mutant --term scale --device cpu \
        --output benchmarks/results/official_terms_mutant_scale40k_H200.json

Each record is also printed as a line; runs cut short by a deadline leave their curves in the log:

    python benchmarks/official_terms.py --from-log terms.log --scene /tmp/mutant --gpu H100 \
        --output benchmarks/results/official_terms_mutant_partial_H100.json
"""

from __future__ import annotations

import argparse
import json
import re
import time
from contextlib import contextmanager
from pathlib import Path
from typing import Any, Callable, Dict, Iterator, List, NamedTuple, Optional, Tuple

import torch
import torch.nn.functional as F
from torch import Tensor

TERMS = ("none", "scale", "rotation", "scale+rotation")


class OfficialDeformed(NamedTuple):
    """Deformed geometry as the official code hands it to its rasterizer: scales already activated."""

    means: Tensor
    quats: Tensor
    scales: Tensor


def rotation_matrices(quats: Tensor) -> Tensor:
    """[N, 3, 3] from quaternions (w, x, y, z) by the unit-quaternion formula applied as is, without
    normalising, as the official rasterizer does."""
    from garo_ns.quaternions import quat_to_rotmat

    return quat_to_rotmat(quats, normalise=False)


def official_functions(terms: str) -> Dict[str, Callable[..., Any]]:
    """Replacements for garo_ns.garo_model's `compose`, `activate` and (for `rotation`) `render_splats`."""
    from garo_ns.render.frame import Splats, activate, render_splats

    scale_term, rotation_term = "scale" in terms, "rotation" in terms

    def compose(field: Any, canonical: Any, time: Any) -> OfficialDeformed:
        d_xyz, d_rot, d_scale = field(canonical.means.detach(), time)
        log_scales = canonical.log_scales
        scales = torch.exp(log_scales) + d_scale if scale_term else torch.exp(log_scales + d_scale)
        return OfficialDeformed(canonical.means + d_xyz, F.normalize(canonical.quats, dim=-1) + d_rot, scales)

    def activate_(canonical: Any, deformed: Any) -> Splats:
        if not isinstance(deformed, OfficialDeformed):  # the undeformed Gaussians (warm-up): as the plugin does
            return activate(canonical, deformed)
        colors = torch.cat([canonical.features_dc[:, None, :], canonical.features_rest], dim=1)
        opacities = torch.sigmoid(canonical.opacities).squeeze(-1)
        return Splats(deformed.means, deformed.quats, deformed.scales, opacities, colors)

    def render(splats: Any, view: Any, sh_degree: int, backgrounds: Optional[Tensor], render_mode: str, *rest: Any):
        if not torch.is_grad_enabled():  # evaluation renders the plugin's way; only training matters here
            return render_splats(splats, view, sh_degree, backgrounds, render_mode, *rest)
        from gsplat import rasterization

        m = rotation_matrices(splats.quats) * splats.scales[:, None, :]
        return rasterization(
            means=splats.means,
            quats=None,
            scales=None,
            opacities=splats.opacities,
            colors=splats.colors,
            viewmats=view.viewmat,
            Ks=view.K,
            width=view.width,
            height=view.height,
            sh_degree=sh_degree,
            backgrounds=backgrounds,
            render_mode=render_mode,
            packed=False,
            absgrad=False,
            rasterize_mode="classic",
            covars=m @ m.transpose(1, 2),
        )

    out: Dict[str, Callable[..., Any]] = {"compose": compose, "activate": activate_}
    if rotation_term:
        out["render_splats"] = render
    return out


@contextmanager
def term_in_place(term: str) -> Iterator[Dict[str, int]]:
    """garo_ns.garo_model's functions replaced by the official code's for `term`, in this process only;
    yields how often each replacement has been called. The plugin's own come back on exit (also for the
    rest of a test session)."""
    import garo_ns.garo_model as garo_model

    replaced = official_functions(term) if term != "none" else {}
    calls = {name: 0 for name in replaced}

    def counted(name: str, function: Callable[..., Any]) -> Callable[..., Any]:
        def call(*args: Any, **kwargs: Any) -> Any:
            calls[name] += 1
            return function(*args, **kwargs)

        return call

    originals = {name: getattr(garo_model, name) for name in replaced}
    try:
        for name, function in replaced.items():
            setattr(garo_model, name, counted(name, function))
        yield calls
    finally:
        for name, function in originals.items():
            setattr(garo_model, name, function)


def train(
    scene: Path,
    term: str,
    steps: int,
    every: int,
    work_dir: Path,
    device: str,
    quick: bool = False,
    score: Optional[str] = None,
) -> Dict[str, Any]:
    """Train `deform-splatfacto` with `term` for `steps` steps; the Gaussian count every `every` steps.
    `quick`: the compressed CPU schedule (garo_ns.tools.train.QuickSchedule), for a smoke test. `score`: a split
    to score at the end (PSNR, SSIM, LPIPS), rendered with the term still in place."""
    from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackLocation

    from garo_ns.tools.train import QuickSchedule, make_config, seed_everything

    if term not in TERMS:
        raise ValueError(f"unknown term {term!r} (known: {', '.join(TERMS)})")
    if "rotation" in term and device != "cuda":
        raise ValueError("the rotation term renders through gsplat with covariances: CUDA only")
    if score is not None and "rotation" in term:  # evaluation renders normalised quaternions (see `render`)
        raise ValueError("--score is for the none and scale terms: evaluation would not render the rotation term")
    schedule = QuickSchedule(steps=steps) if quick else None
    config = make_config("deform-splatfacto", scene, work_dir, device=device, schedule=schedule, experiment_name=term)  # type: ignore[arg-type]
    config.max_num_iterations = steps
    config.steps_per_save = 10**9
    seed_everything(config.machine.seed)
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    model = trainer.pipeline.model
    counts: List[Tuple[int, int]] = []
    start = time.time()

    def record(step: int) -> None:
        if step % every == 0 or step == steps - 1:
            counts.append((step, int(model.num_points)))
            # One line per record, so a run stopped by the machine's deadline still leaves its curve in the log.
            print(f"official_terms {term} step {step} gaussians {counts[-1][1]}", flush=True)

    trainer.callbacks.append(TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN_ITERATION], record))
    scores: Dict[str, Any] = {}
    with term_in_place(term) as calls:
        trainer.train()
        trained_calls = dict(calls)
        if score is not None:  # while the term is still in place: the scores are of the model it trained
            scores = score_with_term(trainer.pipeline, Path(scene), score)
    if term != "none" and trained_calls.get("compose", 0) == 0:  # the plugin no longer calls what was replaced
        raise RuntimeError(f"the official {term} term never ran: garo_ns.garo_model no longer calls compose")
    return {
        "scene": Path(scene).name,
        "term": term,
        "steps": steps,
        "quick": quick,
        "gaussians_every": counts,
        "gaussians_end": counts[-1][1] if counts else None,
        "replaced_calls": trained_calls,
        "train_seconds": time.time() - start,
        "score": None if score is None else {k: v for k, v in scores.items() if k != "num_gaussians"},
        # The replaced functions' calls while scoring: at least one per view, or the term was not rendered.
        "replaced_calls_scoring": {name: calls[name] - trained_calls[name] for name in calls},
        "gpu": torch.cuda.get_device_name() if device == "cuda" else "cpu",
        "git_commit": _commit(),
    }


def score_with_term(pipeline: Any, scene: Path, split: str) -> Dict[str, Any]:
    """PSNR, SSIM and LPIPS of `split`, each frame composed by the field as trained (`exact`): outside
    training the plugin renders through its frame path, which composes the deformation itself and would
    leave a replaced `compose` out (a model trained with the official scale term, rendered the plugin's way,
    scored 23.8 dB on mutant)."""
    from garo_ns.tools.eval import evaluate

    model = pipeline.model
    as_trained = model.gaussians_at
    model.gaussians_at = lambda time, exact=False, settings=None: as_trained(time, exact=True)
    try:
        return evaluate(pipeline, scene, split)
    finally:
        del model.gaussians_at  # the class's method again


def rescore(run_dir: Path, scene: Path, term: str, split: str, device: str, result: Path) -> Dict[str, Any]:
    """Score the checkpoint of a finished run (`run_dir`: the run's nerfstudio_models/ folder) again with
    `term` in place, and write the score into its result file `result` (recording where it was scored)."""
    from garo_ns.tools.train import QuickSchedule, make_config

    record = json.loads(result.read_text())
    if record.get("term") != term or record.get("scene") != Path(scene).name:
        raise ValueError(f"{result} is the {record.get('term')} term on {record.get('scene')}, not {term} on {scene}")
    # The model as the run built it: the compressed CPU schedule also shrinks the field.
    schedule = QuickSchedule(steps=record["steps"]) if record.get("quick") else None
    config = make_config("deform-splatfacto", scene, run_dir.parent / "rescore", device=device, schedule=schedule)  # type: ignore[arg-type]
    config.load_dir = Path(run_dir)
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    if int(trainer.pipeline.model.num_points) != record.get("gaussians_end"):
        raise ValueError(
            f"{run_dir} holds {trainer.pipeline.model.num_points} Gaussians, {result} ended with "
            f"{record.get('gaussians_end')}: not this run's checkpoint"
        )
    with term_in_place(term) as calls:
        scores = score_with_term(trainer.pipeline, Path(scene), split)
    record["score"] = {k: v for k, v in scores.items() if k != "num_gaussians"}
    record["replaced_calls_scoring"] = calls
    record["scored"] = {
        "device": device if device == "cpu" else torch.cuda.get_device_name(),
        "git_commit": _commit(),
        "how": "the run's checkpoint scored again by --rescore",
    }
    result.write_text(json.dumps(record, indent=1) + "\n")
    return record


def _commit() -> Optional[str]:
    import os
    import subprocess

    if os.environ.get("GARO_GIT_COMMIT"):
        return os.environ["GARO_GIT_COMMIT"]
    try:
        return subprocess.run(["git", "rev-parse", "HEAD"], capture_output=True, text=True, check=True).stdout.strip()
    except (OSError, subprocess.CalledProcessError):
        return None


LOG_LINE = re.compile(r"^official_terms (\S+) step (\d+) gaussians (\d+)$")


def curves_from_log(text: str) -> Dict[str, List[Tuple[int, int]]]:
    """Each term's (step, Gaussians) records from the lines `train` prints, in step order: what a run cut
    short (a machine's deadline) leaves. Lines of other output, and of terms not in TERMS, are skipped."""
    curves: Dict[str, Dict[int, int]] = {}
    for line in text.splitlines():
        match = LOG_LINE.match(line.strip())
        if match and match[1] in TERMS:
            curves.setdefault(match[1], {})[int(match[2])] = int(match[3])
    return {term: sorted(points.items()) for term, points in curves.items()}


def from_log(log: Path, scene: str, steps: int, gpu: Optional[str]) -> Dict[str, Any]:
    """The result file of runs cut short, from their log: per term, the counts recorded and the last step
    reached, beside the same step of every other term (the last step all of them reached)."""
    curves = curves_from_log(log.read_text())
    if not curves:
        raise ValueError(f"{log}: no `official_terms <term> step <n> gaussians <m>` lines")
    common = min(points[-1][0] for points in curves.values())
    return {
        "scene": scene,
        "steps_planned": steps,
        "cut_short": any(points[-1][0] < steps - 1 for points in curves.values()),
        "source_log": log.name,
        "common_step": common,
        "gaussians_at_common_step": {term: dict(points)[common] for term, points in curves.items()},
        "terms": {term: {"gaussians_every": points, "last_step": points[-1][0]} for term, points in curves.items()},
        "gpu": gpu,
        "git_commit": _commit(),
    }


def main(argv: Optional[List[str]] = None) -> Dict[str, Any]:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--from-log", type=Path, default=None, help="write the result of runs cut short from their log")
    parser.add_argument("--gpu", default=None, help="with --from-log: the GPU the log's runs used")
    parser.add_argument("--scene", type=Path, required=True)
    parser.add_argument("--term", choices=TERMS, default=None, help="required unless --from-log")
    parser.add_argument("--steps", type=int, default=15000)
    parser.add_argument("--every", type=int, default=500)
    parser.add_argument("--work-dir", type=Path, default=Path("runs/official_terms"))
    parser.add_argument("--device", choices=("cuda", "cpu"), default="cuda")
    parser.add_argument("--quick", action="store_true", help="the compressed CPU schedule (a smoke test)")
    parser.add_argument("--score", choices=("val", "test"), default=None, help="score this split at the end")
    parser.add_argument(
        "--rescore",
        type=Path,
        default=None,
        help="a finished run's nerfstudio_models/ folder: "
        "score it again (--score, default test) into its result file --output",
    )
    parser.add_argument("--output", type=Path, required=True)
    args = parser.parse_args(argv)
    if args.rescore is not None:
        if args.term is None:
            parser.error("--rescore needs the --term the run trained with")
        result = rescore(args.rescore, args.scene, args.term, args.score or "test", args.device, args.output)
        print(json.dumps(result["score"]))
        return result
    if args.from_log is not None:
        result = from_log(args.from_log, args.scene.name, args.steps, args.gpu)
        args.output.parent.mkdir(parents=True, exist_ok=True)
        args.output.write_text(json.dumps(result, indent=1) + "\n")
        print(json.dumps(result["gaussians_at_common_step"] | {"step": result["common_step"]}))
        return result
    if args.term is None:
        parser.error("--term is required to train (or give --from-log)")
    result = train(args.scene, args.term, args.steps, args.every, args.work_dir, args.device, args.quick, args.score)
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(json.dumps(result, indent=1) + "\n")
    print(json.dumps({k: v for k, v in result.items() if k != "gaussians_every"}))
    return result


if __name__ == "__main__":
    main()
