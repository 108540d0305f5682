"""Static resources of the fused deformation kernel (garo_ns/render/fused_kernel.py) per launch config, compiled
ahead of time for a GPU architecture on any machine, no GPU needed: shared memory per program (a program that
needs more than the chip's limit, 227 KB on an H100/H200, does not launch), registers per thread and spilled
bytes (ptxas -v), and whether the products became Hopper's wgmma. A first filter for TUNE_CONFIGS before timing
on a GPU (`benchmarks/deform_mlp.py`, rows `fused` and `fused_tuned`).

    python benchmarks/fused_kernel_resources.py                   # the recipe's field, every TUNE_CONFIG, sm_90
    python benchmarks/fused_kernel_resources.py --configs m64-n64-w8-s2 --arch 90 --output results.json

Uses Triton's compiler entry points (triton.compile with an ASTSource and a GPUTarget) and the ptxas it
bundles; about 5 s a config on one CPU core.
"""

from __future__ import annotations

import argparse
import json
import os
import re
import subprocess
import tempfile
from pathlib import Path
from typing import Any, Dict, Optional, Sequence

from garo_ns.render import fused_field

SMEM_LIMIT = 232448  # bytes of shared memory a program may use on an H100 / H200 (227 KB)


def compile_config(
    config: fused_field.FusedConfig, arch: int = 90, width: int = 256, depth: int = 8, skip_layer: int = 5
) -> Dict[str, Any]:
    """Compile the kernel for `arch` at `config` (the recipe's field by default) and report its resources."""
    import triton
    from triton.backends.compiler import GPUTarget

    kernel = fused_field.build_kernel(False)
    pointers = ("first_ptr", "skip_ptr", "tvec_ptr", "w_ptr", "b_ptr", "hw_ptr", "hb_ptr", "out_ptr")
    kinds = ("*fp16", "*fp16", "*fp32", "*fp16", "*fp32", "*fp16", "*fp32", "*fp32")
    constexprs = {
        "WIDTH": width,
        "DEPTH": depth,
        "SKIP_LAYER": skip_layer,
        "HEADS": 10,
        "HEADS_P": 16,
        "BLOCK_M": config.block_m,
        "BLOCK_N": min(config.block_n, width),
        "STAGES": config.num_stages,
    }
    signature = {**dict(zip(pointers, kinds)), "n": "i32", **{k: "constexpr" for k in constexprs}}
    attrs = {(i,): [["tt.divisibility", 16]] for i in range(len(pointers))}  # torch's allocations are aligned
    source = triton.compiler.ASTSource(fn=kernel, signature=signature, constexprs=constexprs, attrs=attrs)
    compiled = triton.compile(
        source,
        target=GPUTarget("cuda", arch, 32),
        options={"num_warps": config.num_warps, "num_stages": config.num_stages},
    )
    ptx = compiled.asm["ptx"]
    row: Dict[str, Any] = {
        "shared_bytes": int(compiled.metadata.shared),
        "fits": compiled.metadata.shared <= SMEM_LIMIT,
    }
    row["wgmma"] = ptx.count("wgmma.mma_async")
    row["mma_sync"] = ptx.count("mma.sync")
    ptxas = Path(triton.__file__).parent / "backends" / "nvidia" / "bin" / "ptxas"
    with tempfile.TemporaryDirectory() as tmp:
        path = os.path.join(tmp, "kernel.ptx")
        Path(path).write_text(ptx)
        gpu = f"sm_{arch}a" if arch == 90 else f"sm_{arch}"
        report = subprocess.run(
            [str(ptxas), "-v", "--gpu-name", gpu, path, "-o", os.devnull], capture_output=True, text=True
        ).stderr
    registers = re.search(r"Used (\d+) registers", report)
    spills = re.search(r"(\d+) bytes spill stores, (\d+) bytes spill loads", report)
    row["registers"] = int(registers.group(1)) if registers else None
    row["spill_store_bytes"] = int(spills.group(1)) if spills else None
    row["spill_load_bytes"] = int(spills.group(2)) if spills else None
    row["ptxas_notes"] = sorted(set(re.findall(r"\((C\d+)\)", report)))  # e.g. C7519: wgmma serialised by registers
    return row


def main(argv: Optional[Sequence[str]] = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--configs", nargs="+", default=None, help="e.g. m64-n64-w8-s2 (default: every TUNE_CONFIG)")
    p.add_argument("--arch", type=int, default=90, help="compute capability x 10 (90: H100 / H200)")
    p.add_argument("--output", type=Path, default=None, help="write the table as JSON here")
    a = p.parse_args(argv)
    configs = [fused_field.parse_config(c) for c in a.configs] if a.configs else list(fused_field.TUNE_CONFIGS)
    table: Dict[str, Any] = {}
    for config in configs:
        name = fused_field.config_name(config)
        try:
            table[name] = compile_config(config, a.arch)
        except Exception as e:  # a config the compiler rejects is a result
            table[name] = {"error": f"{type(e).__name__}: {str(e).strip().splitlines()[-1][:200]}"}
        print(name, json.dumps(table[name]), flush=True)
    if a.output is not None:
        a.output.write_text(json.dumps({"arch": a.arch, "smem_limit": SMEM_LIMIT, "configs": table}, indent=1) + "\n")


if __name__ == "__main__":
    main()
