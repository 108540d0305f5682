"""Does the deformation field survive its first steps? Replicas of a short training, per MLP head
initialisation, with the field's health (garo_ns.deformation.field_health) every `--every` steps.

A collapsed field (a hidden layer all dead, or offsets that no longer change with time) renders the
scene as static for the rest of training. Each replica is its own process (one seed each); all
share the listed GPUs round-robin. No evaluation: the health record and the training PSNR of the
last steps are what this measures.

    python benchmarks/deform_health.py --scene /tmp/lego --seeds 0 1 2 3 --inits zero default \
        --iterations 4500 --gpus 0 --output deform_health.json
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import time
from pathlib import Path


def train_replica(a: argparse.Namespace, init: str, seed: int) -> dict:
    """Train one replica in this process; its health record, training PSNR and size."""
    import torch
    from nerfstudio.engine.callbacks import TrainingCallback, TrainingCallbackLocation

    from garo_ns.tools.train import make_config, seed_everything

    config = make_config(
        "deform-splatfacto", a.scene, a.work_dir, device=a.device, eval_split="val", experiment_name=f"{init}-{seed}"
    )
    config.machine.seed = seed
    config.max_num_iterations = a.iterations
    config.steps_per_save = 10**9
    model_cfg = config.pipeline.model
    model_cfg.deform_head_init = init
    model_cfg.health_every = a.every
    if a.deform_warmup is not None:
        model_cfg.deform_warmup = a.deform_warmup
    seed_everything(seed)
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    model = trainer.pipeline.model
    psnr: list = []
    last: dict = {}
    metrics_of = model.get_metrics_dict

    def capture(outputs, batch):  # the training batch's PSNR, as the trainer computes it
        metrics = metrics_of(outputs, batch)
        last.update(metrics)
        return metrics

    model.get_metrics_dict = capture

    def record(step: int) -> None:
        if step % a.every == 0 and "psnr" in last:
            psnr.append([step, float(last["psnr"])])

    trainer.callbacks.append(TrainingCallback([TrainingCallbackLocation.AFTER_TRAIN_ITERATION], record))
    start = time.perf_counter()
    trainer.train()
    return {
        "init": init,
        "seed": seed,
        "iterations": a.iterations,
        "train_seconds": time.perf_counter() - start,
        "num_gaussians": int(model.num_points),
        "collapsed": any(h["collapsed"] for h in model.health_log),
        "health": model.health_log,
        "train_psnr": psnr,
        "gpu": torch.cuda.get_device_name(0) if a.device == "cuda" else None,
    }


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--scene", type=Path, required=True)
    p.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2, 3])
    p.add_argument("--inits", nargs="+", default=["zero", "default"])
    p.add_argument("--iterations", type=int, default=4500)
    p.add_argument("--every", type=int, default=100)
    p.add_argument("--deform-warmup", type=int, default=None, help="override (CPU smoke runs)")
    p.add_argument("--device", choices=["cuda", "cpu"], default="cuda")
    p.add_argument("--gpus", nargs="+", default=["0"])
    p.add_argument("--work-dir", type=Path, default=Path("runs/deform_health"))
    p.add_argument("--output", type=Path, default=Path("deform_health.json"))
    p.add_argument("--worker", nargs=2, metavar=("INIT", "SEED"))
    a = p.parse_args()
    if a.worker:
        init, seed = a.worker[0], int(a.worker[1])
        out = train_replica(a, init, seed)
        (a.work_dir / f"{init}-{seed}.json").write_text(json.dumps(out))
        return
    a.work_dir.mkdir(parents=True, exist_ok=True)
    procs = []
    for i, (init, seed) in enumerate((init, seed) for init in a.inits for seed in a.seeds):
        env = {**os.environ, "CUDA_VISIBLE_DEVICES": a.gpus[i % len(a.gpus)]}
        cmd = [sys.executable, __file__, "--scene", str(a.scene), "--iterations", str(a.iterations)]
        cmd += ["--every", str(a.every), "--work-dir", str(a.work_dir), "--device", a.device]
        cmd += [] if a.deform_warmup is None else ["--deform-warmup", str(a.deform_warmup)]
        cmd += ["--worker", init, str(seed)]
        log = open(a.work_dir / f"{init}-{seed}.log", "w")
        procs.append((init, seed, subprocess.Popen(cmd, env=env, stdout=log, stderr=subprocess.STDOUT)))
        if a.device != "cuda":
            procs[-1][2].wait()  # on a CPU the replicas would only compete for memory and cores
    runs = []
    for init, seed, proc in procs:
        proc.wait()
        path = a.work_dir / f"{init}-{seed}.json"
        runs.append(
            json.loads(path.read_text()) if path.exists() else {"init": init, "seed": seed, "error": proc.returncode}
        )
    summary = {
        init: {
            "replicas": sum(r["init"] == init for r in runs),
            "collapsed": sum(r["init"] == init and bool(r.get("collapsed")) for r in runs),
            "failed": sum(r["init"] == init and "error" in r for r in runs),
        }
        for init in a.inits
    }
    result = {"scene": a.scene.name, "iterations": a.iterations, "summary": summary, "runs": runs}
    a.output.parent.mkdir(parents=True, exist_ok=True)
    a.output.write_text(json.dumps(result, indent=1))
    print(json.dumps(summary, indent=1))
    for r in runs:
        if "health" in r:
            last = r["health"][-1] if r["health"] else {}
            first_bad = next((h["step"] for h in r["health"] if h["collapsed"]), None)
            print(
                r["init"],
                r["seed"],
                "collapsed at",
                first_bad,
                "last",
                {k: last.get(k) for k in ("time_sensitivity", "mean_offset", "dead_fraction")},
                "psnr",
                r["train_psnr"][-1:],
            )


if __name__ == "__main__":
    main()
