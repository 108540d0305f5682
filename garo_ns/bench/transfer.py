"""Carry a trained benchmark arm from one run to another.

A GPU machine is held for a limited time. Where the two arms of a scene do not both train inside one
hold, one arm is trained and exported in the first hold, and the second hold trains the other arm and
imports the first: phase 2 of that run then evaluates and times both, one at a time, on one machine,
so their FPS ratio still comes from one run.

An export is a folder: `record.json` (the training record plus where it trained), `config.yml` and
`model.ckpt`, the last checkpoint without optimizer or scheduler state (only the pipeline is needed
to render, and it is a third of the size).
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path
from typing import Any, Dict, Optional

import torch

from garo_ns.state.checkpoints import checkpoint_name, latest_complete_step
from garo_ns.tools.files import written_atomically

CKPT = "model.ckpt"


def export_run(record: Dict[str, Any], environment: Dict[str, Any], out: Path) -> Path:
    """Write a trained arm (its benchmark record, run config and model) to the folder `out`."""
    import yaml

    config_path = Path(record["config"])
    config = yaml.load(config_path.read_text(), Loader=yaml.Loader)
    folder = config.get_checkpoint_dir()
    source = folder / checkpoint_name(latest_complete_step(folder)[0])
    state = torch.load(source, map_location="cpu", weights_only=False)
    out.mkdir(parents=True, exist_ok=True)
    # Written under a temporary name first: a machine taken back mid-write leaves no half model behind.
    with written_atomically(out / CKPT) as partial:
        torch.save({"step": state["step"], "pipeline": state["pipeline"]}, partial)
    shutil.copyfile(config_path, out / "config.yml")
    trained_in = {key: environment.get(key) for key in ("gpu", "torch", "git_commit")}
    (out / "record.json").write_text(json.dumps({**record, "trained_in": trained_in}, indent=2))
    return out


def trained_elsewhere(trained_in: Any) -> Optional[str]:
    """'GPU, commit abc1234' for an arm imported from an earlier run (its `trained_in`), None for an arm
    trained in the run that reports it: the one wording of the benchmark's, the summary's and the README's
    notes."""
    if not isinstance(trained_in, dict):
        return None
    return f"{trained_in.get('gpu')}, commit {str(trained_in.get('git_commit'))[:7]}"


def import_run(export: Path, work_dir: Path, scene: Path) -> Dict[str, Any]:
    """Lay an export out as this run's own training of that variant would be, under `work_dir`, with
    its data path set to `scene`; returns its record with `config` pointing at the new place."""
    import yaml

    export = Path(export)
    missing = [n for n in ("record.json", "config.yml", CKPT) if not (export / n).is_file()]
    if missing:
        raise FileNotFoundError(f"{export} is not a benchmark export (missing {', '.join(missing)})")
    record = json.loads((export / "record.json").read_text())
    config = yaml.load((export / "config.yml").read_text(), Loader=yaml.Loader)
    config.output_dir = Path(work_dir)
    dm = config.pipeline.datamanager
    trained_on = Path(dm.data if getattr(dm, "data", None) is not None else dm.dataparser.data).name
    if trained_on != Path(scene).name:  # scenes are named by their folder, here and on the GPU machine
        raise ValueError(f"{export} was trained on scene '{trained_on}', not on '{Path(scene).name}'")
    if getattr(dm, "data", None) is not None:
        dm.data = Path(scene)
    dm.dataparser.data = Path(scene)
    checkpoint_dir = config.get_checkpoint_dir()
    checkpoint_dir.mkdir(parents=True, exist_ok=True)
    step = int(record["iterations"]) - 1  # training saves its last step, also when stopped by a deadline
    shutil.copyfile(export / CKPT, checkpoint_dir / checkpoint_name(step))
    config_path = config.get_base_dir() / "config.yml"
    config_path.write_text(yaml.dump(config), "utf8")
    record["config"] = str(config_path)
    (Path(work_dir) / f"{record['variant']}.record.json").write_text(json.dumps(record, indent=2))
    return record
