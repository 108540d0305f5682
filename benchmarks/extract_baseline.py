"""Write the baseline's record (deform-splatfacto) out of a benchmark result, in the shape the
deformable-model issue asks for.

    python benchmarks/extract_baseline.py benchmarks/results/lego_H200.json \
        benchmarks/results/lego_deform_splatfacto.json
"""

from __future__ import annotations

import json
import sys
from pathlib import Path


def main() -> None:
    src, dst = Path(sys.argv[1]), Path(sys.argv[2])
    bench = json.loads(src.read_text())
    base = bench["variants"]["deform-splatfacto"]
    out = {
        "source": str(src),
        "method": "deform-splatfacto",
        "scene": bench["scene"],
        "gpu": bench["gpu"],
        "torch": bench["torch"],
        "git_commit": bench["git_commit"],
        "split": bench["split"],
        "background": bench["background"],
        "iterations": base["iterations"],
        "shortened": base["shortened"],
        **{
            k: base[k]
            for k in (
                "psnr",
                "ssim",
                "lpips",
                "num_gaussians",
                "fps",
                "ms_deformation",
                "ms_rasterization",
                "train_seconds",
                "train_steps_per_second",
                "model_size_mb",
            )
        },
        "fps_protocol": bench["fps_protocol"],
        "reference_official_d3dgs": {
            "gpu": "H100",
            "iterations": 32500,
            "psnr": 28.49,
            "ssim": 0.945,
            "lpips": 0.049,
            "num_gaussians": 127000,
            "fps": 158,
        },
    }
    dst.write_text(json.dumps(out, indent=2) + "\n")
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
