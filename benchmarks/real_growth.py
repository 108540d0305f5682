"""Where densification grows on a real capture: one row per refinement, for arms that differ by model settings.

    python benchmarks/real_growth.py --scene CAPTURE --steps 8000 --arm budget --set max_gaussians=300000 \
        --output runs/real_growth/pillow_budget.json
    python benchmarks/real_growth.py --merge runs/real_growth/*.json --output benchmarks/results/real_growth_<GPU>.json

Each call trains one arm (`--method` with the model settings of `--set`) on the capture; `--merge` gathers arms'
files into one, keyed by scene and arm. At every refinement, before it grows, a row records: the number of
Gaussians; how many have a mean view-space gradient above the threshold (the candidates) and how many of those
are large (split, not cloned); where the candidates lie, as quantiles of their distance from the cameras' centre
in camera extents (far background or the object); the Gaussians larger than the size cull; the training PSNR over
the last interval; step time and GPU memory. A run that fails (out of memory) keeps its rows and records the error.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any, Dict, List, Tuple

import torch

from garo_ns import compat

compat.install()


def train_arm(
    scene: Path, method: str, steps: int, overrides: Dict[str, Any], work: Path, device: str, save: Any = None
) -> Dict[str, Any]:
    """Train one arm and return its refinement rows (`save(result)` after each, so a killed run keeps them)."""
    from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackLocation

    from garo_ns.tools.train import make_config, seed_everything

    config = make_config(method, scene, work, device=device)  # type: ignore[arg-type]
    config.max_num_iterations = steps
    config.steps_per_save = 10**9
    for key, value in overrides.items():  # a dotted key reaches into a nested config (camera_optimizer.mode)
        *path, name = key.split(".")
        target = config.pipeline.model
        for part in path:
            target = getattr(target, part)
        if not hasattr(target, name):
            raise SystemExit(f"real_growth.py: the model config has no setting {key}")
        setattr(target, name, value)
    config.set_timestamp()
    config.save_config()
    seed_everything(config.machine.seed)
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    model = trainer.pipeline.model
    strategy = model.strategy
    centres = trainer.pipeline.datamanager.train_dataset.cameras.camera_to_worlds[:, :3, 3]
    centre = centres.mean(0).to(model.device)
    rows: List[Dict[str, Any]] = []
    psnrs: List[torch.Tensor] = []
    clock = {"t": time.perf_counter(), "step": 0}
    original = model.after_iteration
    original_loss = model.get_loss_dict

    def loss_dict(outputs, batch, metrics_dict=None):
        losses = original_loss(outputs, batch, metrics_dict)
        with torch.no_grad():
            gt = model.ground_truth(outputs, batch)
            psnrs.append(-10 * torch.log10(((outputs["rgb"] - gt) ** 2).mean().clamp_min(1e-10)))
        return losses

    def after(step: int) -> None:
        refine = step % strategy.refine_every == 0 and strategy.refine_start_iter < step < strategy.refine_stop_iter
        if refine:
            with torch.no_grad():
                state = model.strategy_state
                grads = state["grad2d"] / state["count"].clamp_min(1)
                size = torch.exp(model.scales).max(-1).values / model.scene_extent
                high = grads > strategy.grow_grad2d
                far = (model.means - centre).norm(dim=-1) / model.scene_extent
                q = torch.tensor([0.1, 0.5, 0.9], device=far.device)
                sample = far[high][:1_000_000].float()
                if device == "cuda":
                    torch.cuda.synchronize()
                now = time.perf_counter()
                rows.append(
                    {
                        "step": step,
                        "gaussians": model.num_points,
                        "candidates": int(high.sum()),
                        "candidates_large": int((high & (size > strategy.grow_scale3d)).sum()),
                        "candidate_distance_q10_50_90": [float(v) for v in torch.quantile(sample, q)]
                        if len(sample)
                        else [],
                        "all_distance_q10_50_90": [float(v) for v in torch.quantile(far[:1_000_000].float(), q)],
                        "beyond_size_cull": int((size > strategy.prune_scale3d).sum()),
                        "visible_at_all": int((state["count"] > 0).sum()),
                        "train_psnr": float(torch.stack(psnrs).mean()) if psnrs else None,
                        "ms_per_step": 1000 * (now - clock["t"]) / max(step - clock["step"], 1),
                        "memory_mb": torch.cuda.memory_allocated() / 2**20 if device == "cuda" else None,
                        "peak_memory_mb": torch.cuda.max_memory_allocated() / 2**20 if device == "cuda" else None,
                    }
                )
                psnrs.clear()
                print(json.dumps(rows[-1]), flush=True)
                if save is not None:
                    save(result)
        original(step)
        if refine:
            clock.update(t=time.perf_counter(), step=step)

    result: Dict[str, Any] = {"overrides": overrides, "scene_extent": model.scene_extent, "rows": rows}
    model.after_iteration = after
    model.get_loss_dict = loss_dict
    for callback in trainer.callbacks:
        if getattr(callback, "func", None) == original:
            callback.func = after
    trainer.callbacks.append(TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN_ITERATION], lambda step: None))
    try:
        trainer.train()
        result["finished"] = True
    except Exception as err:  # out of memory: the rows so far are the measurement
        result["finished"] = False
        result["error"] = f"{type(err).__name__}: {str(err)[:300]}"
    result["final_gaussians"] = model.num_points
    return result


def setting(text: str) -> Tuple[str, Any]:
    """`key=value` with the value read as JSON where it parses (numbers, true, null), else as a string."""
    key, _, value = text.partition("=")
    try:
        return key, json.loads(value)
    except json.JSONDecodeError:
        return key, value


def main() -> None:
    """Command line (module docstring)."""
    from garo_ns.bench.benchmark import environment

    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--scene", type=Path)
    parser.add_argument("--method", default="deform-splatfacto-real")
    parser.add_argument("--steps", type=int, default=8000)
    parser.add_argument("--arm", default="recipe")
    parser.add_argument("--set", nargs="*", default=[], help="model settings: key=value (dotted keys nest)")
    parser.add_argument("--work-dir", type=Path, default=Path("runs/real_growth"))
    parser.add_argument("--device", default="cuda")
    parser.add_argument("--merge", nargs="*", type=Path, help="arms' files to gather into --output")
    parser.add_argument("--output", type=Path, required=True)
    args = parser.parse_args()
    args.output.parent.mkdir(parents=True, exist_ok=True)
    if args.merge:
        merged: Dict[str, Any] = {"arms": {}}
        for path in args.merge:
            one = json.loads(path.read_text())
            merged.update({k: v for k, v in one.items() if k != "arm" and k != "result"})
            merged["arms"][f"{one['scene']}/{one['arm']}"] = {"method": one["method"], **one["result"]}
        merged.pop("scene", None)
        merged.pop("method", None)
        args.output.write_text(json.dumps(merged, indent=1))
        return
    overrides = dict(setting(s) for s in args.set)
    head = {**environment(args.device), "scene": args.scene.name, "method": args.method, "steps": args.steps}
    head["arm"] = args.arm

    def save(result: Dict[str, Any]) -> None:
        args.output.write_text(json.dumps({**head, "result": result}, indent=1))

    save(train_arm(args.scene, args.method, args.steps, overrides, args.work_dir / args.arm, args.device, save))


if __name__ == "__main__":
    main()
