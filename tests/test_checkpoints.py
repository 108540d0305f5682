"""No lost runs: checkpoints are written atomically and a run killed mid-save resumes from the last whole one."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from types import SimpleNamespace

import pytest
import torch

import garo_ns.config  # noqa: F401  (registers the methods; patches nerfstudio's trainer as ns-train does)
from garo_ns.errors import GaroInputError
from garo_ns.state.checkpoints import (
    PARTIAL_PREFIX,
    SLOW_WRITE_ENV,
    checkpoint_name,
    is_complete,
    latest_complete_step,
    save_atomically,
)


def test_ns_train_gets_the_crash_safe_trainer():
    """In a fresh `ns-train` process (its imports, in its order), the plugin's patch is on the Trainer."""
    code = (
        "import nerfstudio.scripts.train\n"
        "from nerfstudio.engine.trainer import Trainer\n"
        "print(Trainer.save_checkpoint.__module__, Trainer._load_checkpoint.__module__)\n"
    )
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.split() == ["garo_ns.state.checkpoints", "garo_ns.state.checkpoints"]


def _state(step: int) -> dict:
    return {"step": step, "pipeline": {"w": torch.full((64, 64), float(step))}}


def test_atomic_save_replaces_and_keeps_only_the_latest(tmp_path):
    save_atomically(_state(10), tmp_path, 10, keep_only_latest=True)
    (tmp_path / f"{PARTIAL_PREFIX}{checkpoint_name(15)}.999").write_bytes(b"PK\x03\x04cut")  # a crash's leftover
    save_atomically(_state(20), tmp_path, 20, keep_only_latest=True)
    assert sorted(p.name for p in tmp_path.iterdir()) == [checkpoint_name(20)]
    assert torch.load(tmp_path / checkpoint_name(20))["step"] == 20
    save_atomically(_state(30), tmp_path, 30, keep_only_latest=False)
    assert sorted(p.name for p in tmp_path.iterdir()) == [checkpoint_name(20), checkpoint_name(30)]


def test_a_cut_short_checkpoint_is_never_picked(tmp_path):
    save_atomically(_state(10), tmp_path, 10, keep_only_latest=False)
    data = (tmp_path / checkpoint_name(10)).read_bytes()
    assert is_complete(tmp_path / checkpoint_name(10))
    for cut in (0, 1, len(data) // 2, len(data) - 1):  # stock nerfstudio killed during its in-place write
        (tmp_path / checkpoint_name(20)).write_bytes(data[:cut])
        assert not is_complete(tmp_path / checkpoint_name(20))
        step, skipped = latest_complete_step(tmp_path)
        assert step == 10 and [p.name for p in skipped] == [checkpoint_name(20)]
    (tmp_path / checkpoint_name(10)).write_bytes(data[:100])
    with pytest.raises(GaroInputError, match="no complete"):
        latest_complete_step(tmp_path)


def test_nerfstudio_own_loader_ignores_a_leftover_partial_file(tmp_path):
    """ns-viewer, ns-eval and ns-render load with nerfstudio's eval_load_checkpoint, which parses every file
    name in the folder: a leftover of an interrupted write must neither break it nor be picked."""
    from nerfstudio.utils.eval_utils import eval_load_checkpoint

    save_atomically(_state(20), tmp_path, 20, keep_only_latest=True)
    (tmp_path / f"{PARTIAL_PREFIX}{checkpoint_name(40)}.1234").write_bytes(b"PK\x03\x04")
    loaded = {}
    pipeline = SimpleNamespace(load_pipeline=lambda state, step: loaded.update(state=state, step=step))
    path, step = eval_load_checkpoint(SimpleNamespace(load_dir=tmp_path, load_step=None), pipeline)
    assert step == 20 and path.name == checkpoint_name(20) and loaded["step"] == 20


TRAIN_SCRIPT = textwrap.dedent(
    """
    import sys
    from pathlib import Path
    from garo_ns.tools.train import QuickSchedule, make_config, train

    config = make_config(
        "garo-deform", Path(sys.argv[1]), Path(sys.argv[2]), experiment_name="killed",
        schedule=QuickSchedule(steps=60, num_random=1500, deform_width=32, deform_depth=2, deform_skip=0),
    )
    config.steps_per_save = 20
    train(config)
    """
)


def _wait_for(predicate, proc: subprocess.Popen, timeout: float) -> None:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        if predicate():
            return
        if proc.poll() is not None:
            raise AssertionError(f"training ended (rc {proc.returncode}) before the save was interrupted")
        time.sleep(0.05)
    proc.kill()
    raise AssertionError("timed out waiting for the checkpoint write")


@pytest.mark.slow
def test_killed_during_save_resumes_from_the_previous_checkpoint(scene_dir, tmp_path):
    import yaml

    out = tmp_path / "runs"
    # The save of step 40 pauses for a minute after its first bytes are on disk: the kill lands mid-write.
    env = dict(os.environ, TORCHDYNAMO_DISABLE="1", **{SLOW_WRITE_ENV: "40:60"})
    log = (tmp_path / "train.log").open("w")
    proc = subprocess.Popen(
        [sys.executable, "-c", TRAIN_SCRIPT, str(scene_dir), str(out)], env=env, stdout=log, stderr=subprocess.STDOUT
    )
    ckpt_dir = out / "killed" / "garo-deform"

    def partial_files():
        # Only step 40's write pauses; an earlier write caught in flight (a loaded machine) is not the kill's target.
        pattern = f"{PARTIAL_PREFIX}{checkpoint_name(40)}*"
        return [p for p in ckpt_dir.rglob(pattern) if p.stat().st_size > 0]

    try:
        _wait_for(lambda: bool(partial_files()), proc, timeout=600)
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        log.close()
    [partial] = partial_files()
    models = partial.parent
    assert sorted(p.name for p in models.glob(f"{PARTIAL_PREFIX}*")) == [partial.name]
    assert not is_complete(partial)
    # The checkpoint that was good before the crash is still there, whole; no step-40 file exists.
    assert sorted(p.name for p in models.glob("*.ckpt")) == [checkpoint_name(20)]
    saved = torch.load(models / checkpoint_name(20), map_location="cpu", weights_only=False)
    assert saved["step"] == 20

    # Resume as `ns-train garo-deform --load-dir <models>` does.
    config = yaml.load((models.parent / "config.yml").read_text(), Loader=yaml.Loader)
    config.experiment_name, config.load_dir, config.max_num_iterations = "resumed", models, 10
    config.set_timestamp()
    config.save_config()
    trainer = config.setup(local_rank=0, world_size=1)
    trainer.setup()
    model = trainer.pipeline.model
    assert trainer._start_step == 21 and model.step == 20

    # Same Gaussians and deformation network.
    now = trainer.pipeline.state_dict()
    tensors = {k: v for k, v in saved["pipeline"].items() if torch.is_tensor(v)}
    assert any(k.startswith("_model.gauss_params.") for k in tensors)
    for key, value in tensors.items():
        assert torch.equal(now[key].cpu(), value), key
    # Same optimizer state (Adam moments and step counts of every parameter group).
    for name, expected in saved["optimizers"].items():
        got = trainer.optimizers.optimizers[name].state_dict()
        assert got["state"].keys() == expected["state"].keys(), name
        for idx, slots in expected["state"].items():
            for slot, value in slots.items():
                assert torch.equal(torch.as_tensor(got["state"][idx][slot]).cpu(), torch.as_tensor(value)), (name, slot)
        assert [g["lr"] for g in got["param_groups"]] == [g["lr"] for g in expected["param_groups"]], name
    # Same densification state (gradient accumulators, GARO activity, static classification).
    [extra_key] = [k for k in saved["pipeline"] if k.endswith("_extra_state")]
    expected_strategy = saved["pipeline"][extra_key]["strategy_state"]
    assert any(torch.is_tensor(v) and v.numel() > 0 for v in expected_strategy.values())
    for key, value in expected_strategy.items():
        if torch.is_tensor(value):
            assert torch.equal(model.strategy_state[key].cpu(), value), key
        else:
            assert model.strategy_state[key] == value, key

    # Training goes on in the new run folder (as ns-train does); the crashed run's checkpoint stays.
    trainer.train()
    assert sorted(p.name for p in trainer.checkpoint_dir.iterdir()) == [checkpoint_name(30)]
    assert is_complete(models / checkpoint_name(20))


@pytest.mark.parametrize("writer", ["numpy.core.multiarray", "numpy._core.multiarray"])
def test_a_checkpoint_of_either_numpy_loads_weights_only(tmp_path, writer):
    """nerfstudio's schedulers leave numpy scalars in a checkpoint, named by the module of the numpy that
    wrote it (numpy 2 on the GPU machine, 1.x elsewhere): a run trained under one loads under the other."""
    import io

    import numpy as np

    from garo_ns.compat import allow_numpy_scalars_in_checkpoints

    buffer = io.BytesIO()  # the legacy format keeps the pickle's global names as plain text, so one can be renamed
    torch.save({"_last_lr": [np.float64(0.25)]}, buffer, _use_new_zipfile_serialization=False)
    data = buffer.getvalue()
    here = next(m for m in ("numpy.core.multiarray", "numpy._core.multiarray") if f"{m}\nscalar".encode() in data)
    data = data.replace(f"{here}\nscalar".encode(), f"{writer}\nscalar".encode())
    allow_numpy_scalars_in_checkpoints()
    assert torch.load(io.BytesIO(data), weights_only=True) == {"_last_lr": [0.25]}


def test_a_full_disk_is_one_line_and_the_previous_checkpoint_stays(tmp_path, monkeypatch):
    from garo_ns.errors import GaroTrainingError
    from garo_ns.state import checkpoints

    checkpoints.save_atomically({"step": 1, "x": torch.ones(3)}, tmp_path, 1, True)
    real_save = torch.save

    def full_disk(obj, f, *args, **kwargs):
        f.write(b"PK\x03\x04 partial")
        raise RuntimeError(
            "[enforce fail at inline_container.cc:778] . PytorchStreamWriter failed writing file "
            "data/0: file write failed; unexpected pos 448 vs 320"
        )

    monkeypatch.setattr(torch, "save", full_disk)
    with pytest.raises(GaroTrainingError, match="disk .* is full.*step-000000001.ckpt is kept"):
        checkpoints.save_atomically({"step": 2}, tmp_path, 2, True)
    monkeypatch.setattr(torch, "save", real_save)
    assert [p.name for p in tmp_path.iterdir()] == ["step-000000001.ckpt"]
    assert checkpoints.is_complete(tmp_path / "step-000000001.ckpt")
