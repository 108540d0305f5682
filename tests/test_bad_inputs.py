"""Bad input ends in one line: broken datasets, checkpoints and flags as a user feeds them to `ns-train` (and a
broken run to `ns-viewer`).

Each row of `CASES` breaks a fresh copy of a valid input one way and runs what the `ns-train` command runs,
in-process (`run_ns_train`: tyro's parse of the arguments, nerfstudio's `main`, then the plugin's handler
for an uncaught error, as the interpreter would call it; `run_ns_viewer` likewise for a row whose arguments start
with "ns-viewer"). Every row must end with a non-zero exit status, exactly one line on stderr that starts with
"error: " and names the file (with its frame, id or key), no traceback, no run folder (ns-viewer: no file of the
run written), within seconds. Two rows also run as real processes, to show that the in-process run says what the
command says. The table in docs/testing.md is generated from the rows.
"""

from __future__ import annotations

import contextlib
import io
import json
import math
import re
import shutil
import subprocess
import sys
import time
import traceback
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable, Dict, List, Tuple

import numpy as np
import pytest
import torch
from test_video_data import make_folder

import garo_ns.config  # noqa: F401  (registers the methods and installs the plugin's nerfstudio hooks)
from garo_ns import compat
from garo_ns.data.nerfds import NerfDSDataParserConfig
from garo_ns.tools.scene import SceneSpec, generate_scene

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "testing.md"
BEGIN, END = "<!-- bad-inputs:begin -->", "<!-- bad-inputs:end -->"
SECONDS = 20.0  # "within seconds": every row, on two shared CPU cores
SPEC = SceneSpec(resolution=16, n_train=3, n_val=1, n_test=1)
# Small model settings, so that the valid run that writes the template checkpoint takes a second; the
# checkpoint rows load with the same ones. One step at most, should a broken input ever reach training.
COMMON = ["--machine.device-type", "cpu", "--vis", "tensorboard", "--max-num-iterations", "1"]
MODEL = ["--pipeline.model.num-random", "200", "--pipeline.model.deform-width", "16"]


@dataclass
class Outcome:
    """What a run of ns-train left: exit status, printed text, time, and whether a run folder exists."""

    status: int
    stdout: str
    stderr: str
    seconds: float
    run_files: List[Path]


def with_output(args: List[str], out: Path) -> List[str]:
    """`args` with `--output-dir OUT` after the method (before any dataparser subcommand, as tyro needs)."""
    return [args[0], "--output-dir", str(out), *args[1:]]


def run_ns_train(args: List[str], out: Path) -> Outcome:
    """`ns-train ARGS --output-dir OUT` in this process, as the command runs it (nerfstudio's entrypoint
    is `main(tyro.cli(...))`); an uncaught error goes to the plugin's excepthook, a traceback for anything
    not a GaroError, printed to the captured stderr, and exit status 1, as the interpreter gives it."""
    import tyro
    from nerfstudio.configs.method_configs import AnnotatedBaseConfigUnion
    from nerfstudio.scripts import train as ns_train

    outcome = run_in_process(lambda: ns_train.main(tyro.cli(AnnotatedBaseConfigUnion, args=with_output(args, out))))
    outcome.run_files = sorted(p for p in out.rglob("*")) if out.exists() else []
    return outcome


def files_of(folder: Path) -> Dict[Path, Tuple[int, int]]:
    """Every file under `folder` with its size and modification time."""
    return {p: (p.stat().st_size, p.stat().st_mtime_ns) for p in folder.rglob("*") if p.is_file()}


def run_ns_viewer(args: List[str], run: Path) -> Outcome:
    """`ns-viewer ARGS` (args[0] is "ns-viewer") in this process, as its entrypoint runs it, reported as
    `run_ns_train` reports; `run_files` are the files under the run folder `run` it created or changed."""
    import tyro
    from nerfstudio.scripts.viewer.run_viewer import RunViewer

    before = files_of(run)
    outcome = run_in_process(lambda: tyro.cli(tyro.conf.FlagConversionOff[RunViewer], args=args[1:]).main())
    after = files_of(run)
    outcome.run_files = sorted(p for p in after if before.get(p) != after[p])
    return outcome


def run_in_process(command: Callable[[], Any]) -> Outcome:
    """Run `command` with its output captured, as the interpreter runs a command: an uncaught error goes to the
    plugin's excepthook (a traceback for anything not a GaroError), exit status 1."""
    stdout, stderr = io.StringIO(), io.StringIO()
    status = 0
    start = time.perf_counter()
    previous = compat._previous_hook
    compat._previous_hook = lambda kind, err, tb: traceback.print_exception(kind, err, tb)  # to captured stderr
    try:
        with contextlib.redirect_stdout(stdout), contextlib.redirect_stderr(stderr):
            try:
                command()
            except SystemExit as err:
                status = err.code if isinstance(err.code, int) else 1
                if err.code is not None and not isinstance(err.code, int):
                    print(err.code, file=sys.stderr)
            except Exception as err:
                compat._excepthook(type(err), err, err.__traceback__)
                status = 1
    finally:
        compat._previous_hook = previous
    return Outcome(status, stdout.getvalue(), stderr.getvalue(), time.perf_counter() - start, [])


# --- valid inputs, copied and broken one way per row -------------------------------------------------------------


class Inputs:
    """Fresh copies of valid inputs for one row: a D-NeRF scene, a NeRF-DS capture, a run's checkpoint folder."""

    def __init__(self, templates: Dict[str, Path], work: Path) -> None:
        work.mkdir(parents=True, exist_ok=True)
        self.templates, self.work = templates, work
        self.copies: Dict[str, Path] = {}

    def _copy(self, name: str) -> Path:
        if name not in self.copies:
            self.copies[name] = Path(shutil.copytree(self.templates[name], self.work / name))
        return self.copies[name]

    def dnerf(self) -> Path:
        return self._copy("scene")

    def nerfds(self) -> Path:
        return self._copy("capture")

    def checkpoints(self) -> Path:
        return self._copy("checkpoints")

    def video(self) -> Path:
        return self._copy("video")

    def run(self) -> Path:
        """A copy of the trained run's folder, its config.yml pointing at the copy (as ns-viewer reads it)."""
        import yaml

        runs = self._copy("runs")
        [path] = runs.glob("*/*/*/config.yml")
        config = yaml.load(path.read_text(), Loader=yaml.Loader)
        config.output_dir = runs
        path.write_text(yaml.dump(config))
        assert config.get_base_dir() == path.parent
        return path.parent

    def dnerf_args(self) -> List[str]:
        return ["garo-deform", *COMMON, *MODEL, "--data", str(self.dnerf())]

    def nerfds_args(self) -> List[str]:
        return ["garo-deform-real", *COMMON, *MODEL, "nerfds-data", "--data", str(self.nerfds())]

    def video_args(self) -> List[str]:
        # The hand-built folder's point cloud has 2 points, too few to seed from.
        parser = ["nerfds-data", "--use-points", "False", "--data", str(self.video())]
        return ["garo-deform-real", *COMMON, *MODEL, *parser]


def edit_json(path: Path, change: Callable[[Any], Any]) -> None:
    """Rewrite a JSON file with `change` applied to it in place."""
    data = json.loads(path.read_text())
    change(data)
    path.write_text(json.dumps(data))


def train_frame(i: int, **values: Any) -> Callable[[Any], None]:
    return lambda m: m["frames"][i].update(values)


def truncate(path: Path, keep: float = 0.5) -> None:
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * keep)])


def checkpoint_path(folder: Path) -> Path:
    return next(folder.glob("step-*.ckpt"))


def rewrite_checkpoint(folder: Path, change: Callable[[Dict[str, Any]], Any]) -> None:
    path = checkpoint_path(folder)
    state = torch.load(path, map_location="cpu", weights_only=False)
    change(state)
    torch.save(state, path)


# Each case: (input, what is broken, build) where build(inputs) breaks a copy and returns ns-train's arguments
# and what the line must name (each as it appears in the line).
Build = Callable[[Inputs], Tuple[List[str], List[str]]]


def dnerf_case(change: Callable[[Path], None], names: Callable[[Path], List[str]]) -> Build:
    def build(inputs: Inputs) -> Tuple[List[str], List[str]]:
        scene = inputs.dnerf()
        change(scene)
        return inputs.dnerf_args(), names(scene)

    return build


def nerfds_case(change: Callable[[Path], None], names: Callable[[Path], List[str]]) -> Build:
    def build(inputs: Inputs) -> Tuple[List[str], List[str]]:
        capture = inputs.nerfds()
        change(capture)
        return inputs.nerfds_args(), names(capture)

    return build


def video_case(change: Callable[[Path], None], names: Callable[[Path], List[str]]) -> Build:
    def build(inputs: Inputs) -> Tuple[List[str], List[str]]:
        folder = inputs.video()
        change(folder)
        return inputs.video_args(), names(folder)

    return build


def checkpoint_case(change: Callable[[Path], None], names: Callable[[Path], List[str]], *extra: str) -> Build:
    def build(inputs: Inputs) -> Tuple[List[str], List[str]]:
        folder = inputs.checkpoints()
        change(folder)
        return [*inputs.dnerf_args(), "--load-dir", str(folder), *extra], names(folder)

    return build


def viewer_case(change: Callable[[Path], None], names: Callable[[Path], List[str]]) -> Build:
    """`ns-viewer` on a copy of the trained run, its checkpoint folder broken by `change`."""

    def build(inputs: Inputs) -> Tuple[List[str], List[str]]:
        run = inputs.run()
        change(run / "nerfstudio_models")
        return ["ns-viewer", "--load-config", str(run / "config.yml")], names(run / "nerfstudio_models")

    return build


def resumed_run(inputs: Inputs, drop: List[str]) -> Tuple[List[str], List[str]]:
    """`ns-train --load-dir` on a copy of the trained run, with its command less the flags `drop` (a flag and its
    value): the line must name the run's config.yml and those flags."""
    run = inputs.run()
    args = inputs.dnerf_args()
    at = args.index(drop[0])
    assert args[at : at + len(drop)] == drop
    args = [*args[:at], *args[at + len(drop) :], "--load-dir", str(run / "nerfstudio_models")]
    return args, [str(checkpoint_path(run / "nerfstudio_models")), str(run / "config.yml"), " ".join(drop)]


def data_elsewhere(data: Callable[[Inputs], Path]) -> Build:
    """garo-deform with `--data` naming something other than a D-NeRF scene's folder."""

    def build(inputs: Inputs) -> Tuple[List[str], List[str]]:
        target = data(inputs)
        return ["garo-deform", *COMMON, *MODEL, "--data", str(target)], [str(target)]

    return build


def flag_case(flags: List[str], names: List[str], real: bool = False) -> Build:
    def build(inputs: Inputs) -> Tuple[List[str], List[str]]:
        args = inputs.nerfds_args() if real else inputs.dnerf_args()
        at = args.index("nerfds-data") + 1 if real else 1  # a dataparser flag goes after its subcommand
        return [*args[:at], *flags, *args[at:]], names

    return build


def frame(i: int, split: str = "train") -> Callable[[Path], List[str]]:
    return lambda d: [f"{d / f'transforms_{split}.json'}, frame {i}"]


def train_json(d: Path) -> Path:
    return d / "transforms_train.json"


def unlink(path: Path) -> None:
    path.unlink()


def as_mode(path: Path, mode: str) -> None:
    """Re-save an image in PIL's pixel `mode` (P: a palette PNG, as PNG compressors write; LA: grey+alpha)."""
    from PIL import Image

    with Image.open(path) as im:
        converted = im.convert("RGBA").convert(mode) if mode != "P" else im.convert("RGB").quantize(16)
    converted.save(path)


def as_fifo(path: Path) -> None:
    import os

    path.unlink()
    os.mkfifo(path)


def wrong_size_image(d: Path) -> None:
    other = generate_scene(d.parent / "bigger", SceneSpec(resolution=20, n_train=1, n_val=1, n_test=1))
    shutil.copy(other / "train" / "r_000.png", d / "train" / "r_001.png")


def other_version_field(state: Dict[str, Any]) -> None:
    pipeline = state["pipeline"]
    key = "_model.deformation.layers.0.weight"
    pipeline[key] = torch.zeros(pipeline[key].shape[0] * 2, pipeline[key].shape[1])


def other_sh_degree(state: Dict[str, Any]) -> None:
    pipeline = state["pipeline"]
    key = "_model.gauss_params.features_rest"
    pipeline[key] = pipeline[key][:, :3].clone()


def without_field(state: Dict[str, Any]) -> None:  # what a splatfacto run's checkpoint holds
    for key in [k for k in state["pipeline"] if k.startswith("_model.deformation.")]:
        del state["pipeline"][key]


CAM = "camera/train_001.json"
VIDEO_FRAME = "images/frame_00002.png"
CASES: List[Tuple[str, str, Build]] = [
    # D-NeRF layout (garo-dnerf-data)
    (
        "D-NeRF",
        "data folder missing",
        lambda i: ([*i.dnerf_args()[:-1], str(i.work / "nowhere")], [str(i.work / "nowhere")]),
    ),
    (
        "D-NeRF",
        "transforms_train.json missing",
        dnerf_case(lambda d: unlink(train_json(d)), lambda d: [str(train_json(d))]),
    ),
    (
        "D-NeRF",
        "transforms_train.json empty",
        dnerf_case(lambda d: train_json(d).write_text(""), lambda d: [str(train_json(d))]),
    ),
    (
        "D-NeRF",
        "transforms_train.json truncated",
        dnerf_case(lambda d: truncate(train_json(d)), lambda d: [str(train_json(d))]),
    ),
    (
        "D-NeRF",
        "transforms file is a list",
        dnerf_case(
            lambda d: train_json(d).write_text(f"[{train_json(d).read_text()}]"), lambda d: [str(train_json(d))]
        ),
    ),
    (
        "D-NeRF",
        "transforms_test.json missing (the eval split)",
        dnerf_case(lambda d: unlink(d / "transforms_test.json"), lambda d: [str(d / "transforms_test.json")]),
    ),
    (
        "D-NeRF",
        "camera_angle_x a string",
        dnerf_case(
            lambda d: edit_json(train_json(d), lambda m: m.update(camera_angle_x="0.69")),
            lambda d: [str(train_json(d)), "camera_angle_x"],
        ),
    ),
    (
        "D-NeRF",
        "no frames",
        dnerf_case(
            lambda d: edit_json(train_json(d), lambda m: m.update(frames=[])),
            lambda d: [str(train_json(d)), "no frames"],
        ),
    ),
    (
        "D-NeRF",
        "a frame not an object",
        dnerf_case(lambda d: edit_json(train_json(d), lambda m: m["frames"].__setitem__(1, [])), frame(1)),
    ),
    (
        "D-NeRF",
        "time missing",
        dnerf_case(lambda d: edit_json(train_json(d), lambda m: m["frames"][2].pop("time")), frame(2)),
    ),
    ("D-NeRF", "time NaN", dnerf_case(lambda d: edit_json(train_json(d), train_frame(1, time=math.nan)), frame(1))),
    ("D-NeRF", "time true", dnerf_case(lambda d: edit_json(train_json(d), train_frame(1, time=True)), frame(1))),
    (
        "D-NeRF",
        "time out of [0, 1]",
        dnerf_case(lambda d: edit_json(train_json(d), train_frame(2, time=1.5)), frame(2)),
    ),
    (
        "D-NeRF",
        "transform_matrix ragged",
        dnerf_case(
            lambda d: edit_json(
                train_json(d), train_frame(1, transform_matrix=[[1, 0, 0, 0], [0, 1, 0], [0, 0, 1, 0], [0, 0, 0, 1]])
            ),
            frame(1),
        ),
    ),
    (
        "D-NeRF",
        "transform_matrix of strings",
        dnerf_case(
            lambda d: edit_json(train_json(d), train_frame(1, transform_matrix=[["1", "0", "0", "0"]] * 4)), frame(1)
        ),
    ),
    (
        "D-NeRF",
        "transform_matrix 3x4",
        dnerf_case(
            lambda d: edit_json(train_json(d), train_frame(0, transform_matrix=np.eye(4)[:3].tolist())), frame(0)
        ),
    ),
    (
        "D-NeRF",
        "transform_matrix with NaN",
        dnerf_case(
            lambda d: edit_json(train_json(d), train_frame(2, transform_matrix=np.full((4, 4), math.nan).tolist())),
            frame(2),
        ),
    ),
    (
        "D-NeRF",
        "file_path missing",
        dnerf_case(lambda d: edit_json(train_json(d), lambda m: m["frames"][1].pop("file_path")), frame(1)),
    ),
    (
        "D-NeRF",
        "file_path ../ outside the folder",
        dnerf_case(
            lambda d: edit_json(train_json(d), train_frame(1, file_path="../train/r_001")),
            lambda d: [*frame(1)(d), "../train/r_001"],
        ),
    ),
    (
        "D-NeRF",
        "file_path absolute",
        dnerf_case(
            lambda d: edit_json(train_json(d), train_frame(2, file_path="/etc/hostname")),
            lambda d: [*frame(2)(d), "/etc/hostname"],
        ),
    ),
    (
        "D-NeRF",
        "transform_matrix all zero",
        dnerf_case(
            lambda d: edit_json(train_json(d), train_frame(1, transform_matrix=np.zeros((4, 4)).tolist())), frame(1)
        ),
    ),
    (
        "D-NeRF",
        "transform_matrix mirrored",
        dnerf_case(
            lambda d: edit_json(
                train_json(d), train_frame(2, transform_matrix=np.diag([1.0, 1.0, -1.0, 1.0]).tolist())
            ),
            frame(2),
        ),
    ),
    ("D-NeRF", "--data a file", data_elsewhere(lambda i: train_json(i.dnerf()))),
    ("D-NeRF", "a real capture given to garo-deform", data_elsewhere(lambda i: i.nerfds())),
    (
        "D-NeRF",
        "image missing",
        dnerf_case(
            lambda d: unlink(d / "train" / "r_002.png"), lambda d: [*frame(2)(d), str(d / "train" / "r_002.png")]
        ),
    ),
    (
        "D-NeRF",
        "image truncated",
        dnerf_case(lambda d: truncate(d / "train" / "r_001.png"), lambda d: [str(d / "train" / "r_001.png")]),
    ),
    (
        "D-NeRF",
        "image empty",
        dnerf_case(lambda d: (d / "train" / "r_000.png").write_bytes(b""), lambda d: [str(d / "train" / "r_000.png")]),
    ),
    (
        "D-NeRF",
        "image not an image",
        dnerf_case(
            lambda d: (d / "train" / "r_000.png").write_text("not a picture"),
            lambda d: [str(d / "train" / "r_000.png")],
        ),
    ),
    (
        "D-NeRF",
        "image a palette PNG",
        dnerf_case(lambda d: as_mode(d / "train" / "r_001.png", "P"), lambda d: [str(d / "train" / "r_001.png")]),
    ),
    (
        "D-NeRF",
        "image grey+alpha",
        dnerf_case(lambda d: as_mode(d / "train" / "r_001.png", "LA"), lambda d: [str(d / "train" / "r_001.png")]),
    ),
    (
        "D-NeRF",
        "image a FIFO",
        dnerf_case(lambda d: as_fifo(d / "train" / "r_001.png"), lambda d: [str(d / "train" / "r_001.png")]),
    ),
    (
        "D-NeRF",
        "images of two sizes",
        dnerf_case(wrong_size_image, lambda d: [*frame(1)(d), str(d / "train" / "r_001.png")]),
    ),
    # NeRF-DS / HyperNeRF layout (nerfds-data)
    (
        "NeRF-DS",
        "dataset.json missing",
        nerfds_case(lambda d: unlink(d / "dataset.json"), lambda d: [str(d / "dataset.json")]),
    ),
    (
        "NeRF-DS",
        "train_ids not a list",
        nerfds_case(
            lambda d: edit_json(d / "dataset.json", lambda m: m.update(train_ids="train_000")),
            lambda d: [str(d / "dataset.json"), "train_ids"],
        ),
    ),
    (
        "NeRF-DS",
        "an id leading outside the folder",
        nerfds_case(
            lambda d: edit_json(d / "dataset.json", lambda m: m["train_ids"].append("../x")),
            lambda d: [str(d / "dataset.json"), "'../x'"],
        ),
    ),
    (
        "NeRF-DS",
        "an id listed twice in train_ids",
        nerfds_case(
            lambda d: edit_json(d / "dataset.json", lambda m: m["train_ids"].append(m["train_ids"][1])),
            lambda d: [str(d / "dataset.json"), "train_ids", "'train_001'"],
        ),
    ),
    (
        "NeRF-DS",
        "an id in both train_ids and val_ids",
        nerfds_case(
            lambda d: edit_json(d / "dataset.json", lambda m: m["val_ids"].append(m["train_ids"][0])),
            lambda d: [str(d / "dataset.json"), "'train_000'", "both train_ids and val_ids"],
        ),
    ),
    (
        "NeRF-DS",
        "metadata.json lacks an id",
        nerfds_case(
            lambda d: edit_json(d / "metadata.json", lambda m: m.pop("train_001")),
            lambda d: [str(d / "metadata.json"), "train_001"],
        ),
    ),
    (
        "NeRF-DS",
        "time a string",
        nerfds_case(
            lambda d: edit_json(d / "metadata.json", lambda m: m["train_002"].update(time="0.5")),
            lambda d: [str(d / "metadata.json"), "train_002"],
        ),
    ),
    ("NeRF-DS", "camera file missing", nerfds_case(lambda d: unlink(d / CAM), lambda d: [str(d / CAM)])),
    (
        "NeRF-DS",
        "orientation ragged",
        nerfds_case(
            lambda d: edit_json(d / CAM, lambda c: c.update(orientation=[[1, 0, 0], [0, 1], [0, 0, 1]])),
            lambda d: [str(d / CAM), "train_001", "orientation"],
        ),
    ),
    (
        "NeRF-DS",
        "focal_length negative",
        nerfds_case(
            lambda d: edit_json(d / CAM, lambda c: c.update(focal_length=-5.0)), lambda d: [str(d / CAM), "train_001"]
        ),
    ),
    (
        "NeRF-DS",
        "image_size of strings",
        nerfds_case(
            lambda d: edit_json(d / CAM, lambda c: c.update(image_size=["16", "16"])),
            lambda d: [str(d / CAM), "image_size"],
        ),
    ),
    (
        "NeRF-DS",
        "scene.json scale zero",
        nerfds_case(
            lambda d: edit_json(d / "scene.json", lambda s: s.update(scale=0.0)),
            lambda d: [str(d / "scene.json"), "scale"],
        ),
    ),
    (
        "NeRF-DS",
        "image truncated",
        nerfds_case(
            lambda d: truncate(d / "rgb" / "2x" / "train_002.png"), lambda d: [str(d / "rgb" / "2x" / "train_002.png")]
        ),
    ),
    (
        "NeRF-DS",
        "points.npy of strings",
        nerfds_case(
            lambda d: np.save(d / "points.npy", np.array([["a", "b", "c"]])), lambda d: [str(d / "points.npy")]
        ),
    ),
    (
        "NeRF-DS",
        "points.npy of 2 points",
        nerfds_case(lambda d: np.save(d / "points.npy", np.zeros((2, 3))), lambda d: [str(d / "points.npy")]),
    ),
    (
        "NeRF-DS",
        "points.npy of shape [N, 2]",
        nerfds_case(lambda d: np.save(d / "points.npy", np.zeros((5, 2))), lambda d: [str(d / "points.npy")]),
    ),
    (
        "NeRF-DS",
        "points.npy truncated",
        nerfds_case(lambda d: truncate(d / "points.npy"), lambda d: [str(d / "points.npy")]),
    ),
    (
        "NeRF-DS",
        "no val_ids to evaluate on",
        nerfds_case(
            lambda d: edit_json(d / "dataset.json", lambda m: m.update(val_ids=[])),
            lambda d: [str(d / "dataset.json"), "val_ids"],
        ),
    ),
    # A video after ns-process-data, with a time per frame (nerfds-data)
    (
        "video",
        "a file_path listed twice",
        video_case(
            lambda d: edit_json(d / "transforms.json", lambda m: m["frames"][3].update(file_path=VIDEO_FRAME)),
            lambda d: [str(d / "transforms.json"), "frame 3", VIDEO_FRAME],
        ),
    ),
    # Checkpoints (ns-train --load-dir)
    (
        "checkpoint",
        "load folder missing",
        lambda i: ([*i.dnerf_args(), "--load-dir", str(i.work / "none")], [str(i.work / "none")]),
    ),
    ("checkpoint", "truncated", checkpoint_case(lambda f: truncate(checkpoint_path(f)), lambda f: [str(f)])),
    (
        "checkpoint",
        "not a checkpoint (text)",
        checkpoint_case(lambda f: checkpoint_path(f).write_text("hello"), lambda f: [str(f)]),
    ),
    (
        "checkpoint",
        "a zip that holds no pipeline",
        checkpoint_case(
            lambda f: torch.save({"weights": torch.zeros(1)}, checkpoint_path(f)),
            lambda f: [str(checkpoint_path(f)), "pipeline"],
        ),
    ),
    (
        "checkpoint",
        "of another method (no deformation field)",
        checkpoint_case(
            lambda f: rewrite_checkpoint(f, without_field), lambda f: [str(checkpoint_path(f)), "deformation."]
        ),
    ),
    (
        "checkpoint",
        "of another version (field of another width)",
        checkpoint_case(
            lambda f: rewrite_checkpoint(f, other_version_field),
            lambda f: [str(checkpoint_path(f)), "deformation.layers.0.weight"],
        ),
    ),
    (
        "checkpoint",
        "of other settings (SH degree)",
        checkpoint_case(
            lambda f: rewrite_checkpoint(f, other_sh_degree),
            lambda f: [str(checkpoint_path(f)), "gauss_params.features_rest"],
        ),
    ),
    (
        "checkpoint",
        "truncated, opened in ns-viewer",
        viewer_case(lambda f: truncate(checkpoint_path(f)), lambda f: [str(checkpoint_path(f).name), str(f)]),
    ),
    (
        "checkpoint",
        "resumed without the field size its run trained with",
        lambda i: resumed_run(i, drop=["--pipeline.model.deform-width", "16"]),
    ),
    (
        "checkpoint",
        "--load-step of no checkpoint",
        checkpoint_case(lambda f: None, lambda f: [str(f), "step-000000007.ckpt"], "--load-step", "7"),
    ),
    # Flags
    (
        "flag",
        "--pipeline.model.rho-max 2 (out of range)",
        flag_case(["--pipeline.model.rho-max", "2"], ["--pipeline.model.rho-max"]),
    ),
    (
        "flag",
        "--pipeline.model.compact-fraction nan",
        flag_case(["--pipeline.model.compact-fraction", "nan"], ["--pipeline.model.compact-fraction"]),
    ),
    (
        "flag",
        "compact-min-fraction above compact-fraction (contradictory)",
        flag_case(
            ["--pipeline.model.compact-fraction", "0.1", "--pipeline.model.compact-min-fraction", "0.2"],
            ["--pipeline.model.compact-min-fraction"],
        ),
    ),
    (
        "flag",
        "--pipeline.model.use-absgrad True (cannot work)",
        flag_case(["--pipeline.model.use-absgrad", "True"], ["--pipeline.model.use-absgrad"]),
    ),
    (
        "flag",
        "--pipeline.model.k-neighbors 0",
        flag_case(["--pipeline.model.k-neighbors", "0"], ["--pipeline.model.k-neighbors"]),
    ),
    (
        "flag",
        "--pipeline.model.deform-depth 0",
        flag_case(["--pipeline.model.deform-depth", "0"], ["--pipeline.model.deform-depth"]),
    ),
    (
        "flag",
        "--pipeline.model.num-random 2",
        lambda inputs: ([*inputs.dnerf_args(), "--pipeline.model.num-random", "2"], ["--pipeline.model.num-random"]),
    ),
    (
        "flag",
        "--pipeline.model.max-gaussians 0",
        flag_case(["--pipeline.model.max-gaussians", "0"], ["--pipeline.model.max-gaussians"]),
    ),
    (
        "flag",
        "--max-num-iterations 0",
        lambda inputs: ([*inputs.dnerf_args(), "--max-num-iterations", "0"], ["--max-num-iterations"]),
    ),
    (
        "flag",
        "garo-dnerf-data --scale-factor 0",
        lambda inputs: ([*inputs.dnerf_args(), "garo-dnerf-data", "--scale-factor", "0"], ["--scale-factor"]),
    ),
    (
        "flag",
        "nerfds-data --downscale-factor 0",
        flag_case(["--downscale-factor", "0"], ["--downscale-factor"], real=True),
    ),
]


def case_id(case: Tuple[str, str, Build]) -> str:
    return re.sub(r"[^a-z0-9]+", "-", f"{case[0]} {case[1]}".lower()).strip("-")


# --- fixtures ----------------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def templates(tmp_path_factory) -> Dict[str, Path]:
    """A valid scene, capture and run (trained one step through the same in-process ns-train: its
    checkpoint loads with the rows' settings, which shows the rows fail for their breakage alone)."""
    root = tmp_path_factory.mktemp("valid")
    scene = generate_scene(root / "scene", SPEC)
    capture = generate_scene(root / "capture", SPEC, layout="nerfds")
    video = make_folder(root / "video", n=10, times={k: k / 10 for k in range(1, 11)}, downscales=1)
    NerfDSDataParserConfig(data=video, use_points=False).check_data()  # the valid folder passes
    args = ["garo-deform", *COMMON, *MODEL, "--data", str(scene), "--experiment-name", "ok", "--timestamp", "t"]
    outcome = run_ns_train(args, root / "runs")
    assert outcome.status == 0, outcome.stderr[-3000:]
    ckpts = root / "runs" / "ok" / "garo-deform" / "t" / "nerfstudio_models"
    again = run_ns_train([*args[:-4], "--load-dir", str(ckpts)], root / "resumed")  # and loads back
    assert again.status == 0, again.stderr[-3000:]
    return {"scene": scene, "capture": capture, "video": video, "checkpoints": ckpts, "runs": root / "runs"}


ROWS: Dict[str, Tuple[str, str, str]] = {}  # case id -> (input, what, the line with paths as placeholders)


def placeholders(line: str, inputs: Inputs) -> str:
    """The line with this row's copies named as the table names them."""
    for name, path in inputs.copies.items():
        line = line.replace(str(path), f"<{name}>")
    return line.replace(str(inputs.work), "<tmp>")


def run_case(case: Tuple[str, str, Build], templates: Dict[str, Path], work: Path) -> Tuple[Outcome, List[str], Inputs]:
    work.mkdir(parents=True, exist_ok=True)
    inputs = Inputs(templates, work)
    args, names = case[2](inputs)
    if args[0] == "ns-viewer":
        return run_ns_viewer(args, inputs.copies["runs"]), names, inputs
    return run_ns_train(args, work / "outputs"), names, inputs


def assert_one_line(outcome: Outcome, names: List[str]) -> str:
    text = outcome.stdout + outcome.stderr
    assert outcome.status != 0, text[-3000:]
    assert "Traceback" not in text, text[-3000:]
    lines = [line for line in outcome.stderr.splitlines() if line.strip()]
    assert len(lines) == 1 and lines[0].startswith("error: "), text[-3000:]
    for name in names:
        assert name in lines[0], (name, lines[0])
    assert "Saving config" not in text and "TrainerConfig(" not in text, text[:2000]  # before the config dump
    assert outcome.run_files == [], outcome.run_files
    assert outcome.seconds < SECONDS, outcome.seconds
    return lines[0]


@pytest.mark.parametrize("case", CASES, ids=[case_id(c) for c in CASES])
def test_bad_input_ends_in_one_line_naming_it(case, templates, tmp_path):
    outcome, names, inputs = run_case(case, templates, tmp_path)
    line = assert_one_line(outcome, names)
    ROWS[case_id(case)] = (case[0], case[1], placeholders(line, inputs))


def test_the_table_has_every_kind_of_input():
    kinds = {kind for kind, _, _ in CASES}
    assert kinds == {"D-NeRF", "NeRF-DS", "video", "checkpoint", "flag"}
    assert len(CASES) >= 30 and len({case_id(c) for c in CASES}) == len(CASES)


def render_table(rows: Dict[str, Tuple[str, str, str]]) -> str:
    """The docs table: one row per case, in the order of CASES."""
    out = [
        "| Input | Broken how | The one line ns-train (or ns-viewer) prints (exit status 1, nothing written) |",
        "| --- | --- | --- |",
    ]
    for case in CASES:
        kind, what, line = rows[case_id(case)]
        out.append(f"| {kind} | {what} | `{line.replace('|', '/')}` |")
    return "\n".join(out)


def test_docs_table_is_the_one_the_rows_print():
    """Runs after the rows (same module, in order): regenerates the block of docs/testing.md and fails
    when it differed (commit the rewritten page)."""
    missing = [case_id(c) for c in CASES if case_id(c) not in ROWS]
    if missing:
        pytest.skip(f"rows not run in this session: {missing[:3]}")
    text = DOC.read_text()
    assert BEGIN in text and END in text
    head, rest = text.split(BEGIN, 1)
    _, tail = rest.split(END, 1)
    new = f"{head}{BEGIN}\n{render_table(ROWS)}\n{END}{tail}"
    if new != text:
        DOC.write_text(new)
    assert new == text, "docs/testing.md's bad-input table was out of date: rewritten, commit it"


def test_the_flags_a_resume_line_names_resume_the_run(templates, tmp_path):
    """A run trained with a field of other settings than the command's (the demo's runs against the README's resume
    command): the line names the flags, and the command with them added resumes the run (a step after its last)."""
    inputs = Inputs(templates, tmp_path / "work")
    args, names = resumed_run(inputs, drop=["--pipeline.model.deform-width", "16"])
    line = assert_one_line(run_ns_train(args, tmp_path / "refused"), names)
    flags = line.split("; to resume it, add ", 1)[1].removesuffix(" to the command").split()
    assert flags == ["--pipeline.model.deform-width", "16"]
    out = tmp_path / "resumed"
    resumed = run_ns_train([args[0], *flags, *args[1:], "--experiment-name", "r", "--timestamp", "t"], out)
    assert resumed.status == 0, resumed.stderr[-3000:]
    assert sorted(p.name for p in (out / "r" / "garo-deform" / "t" / "nerfstudio_models").glob("*.ckpt")) == [
        "step-000000001.ckpt"
    ]


# --- a few rows as the real command ------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "name", ["flag-pipeline-model-rho-max-2-out-of-range", "checkpoint-truncated-opened-in-ns-viewer"]
)
def test_the_command_prints_what_the_in_process_run_prints(name, templates, tmp_path):
    """A flag row as the real command: parsed by tyro and reported by the installed excepthook, the path
    the in-process run imitates most (dataset rows as commands: test_early_errors.py). The ns-viewer row as
    the command too: it imports the plugin in another order (from inside nerfstudio's eval_utils)."""
    case = next(c for c in CASES if case_id(c) == name)
    inputs = Inputs(templates, tmp_path / "command")
    args, names = case[2](inputs)
    if args[0] == "ns-viewer":
        watched = inputs.copies["runs"]
        command_line = ["-m", "nerfstudio.scripts.viewer.run_viewer", *args[1:]]
    else:
        watched = inputs.work / "outputs"
        command_line = ["-m", "nerfstudio.scripts.train", *with_output(args, watched)]
    before = files_of(watched) if watched.exists() else {}
    # Deprecation warnings that torch and nerfstudio print at import, and the one of a machine without LPIPS's
    # weights (ns-viewer builds the model before it loads), are no part of the report (pytest keeps them from
    # the in-process run's stderr too).
    warnings = ["-W", "ignore::FutureWarning", "-W", "ignore::UserWarning"]
    proc = subprocess.run([sys.executable, *warnings, *command_line], capture_output=True, text=True, timeout=600)
    after = files_of(watched) if watched.exists() else {}
    changed = sorted(p for p in after if before.get(p) != after[p])
    command = Outcome(proc.returncode, proc.stdout, proc.stderr, 0.0, changed)
    line = placeholders(assert_one_line(command, names), inputs)
    outcome, names, in_process = run_case(case, templates, tmp_path / "in_process")
    assert line == placeholders(assert_one_line(outcome, names), in_process)


# --- a valid scene's JSON, mutated at random ---------------------------------------------------------------------


def mutations() -> Any:
    """Hypothesis strategy: (frame index, key, value) replacing one field of one training frame, or a
    top-level key's value, with a value of the wrong kind or out of range."""
    from hypothesis import strategies as st

    junk = st.one_of(
        st.none(),
        st.booleans(),
        st.text(max_size=4),
        st.floats(allow_nan=True, allow_infinity=True).filter(lambda x: not 0 <= x <= 1 or math.isnan(x)),
        st.lists(st.integers(-2, 2), max_size=5),
        st.lists(st.lists(st.one_of(st.floats(allow_nan=True), st.text(max_size=2)), max_size=5), max_size=5),
        st.dictionaries(st.text(max_size=3), st.integers(), max_size=2),
    )
    field = st.sampled_from(["time", "transform_matrix", "file_path"])
    return st.tuples(st.integers(0, SPEC.n_train - 1), field, junk)


def is_pose(value: Any) -> bool:
    """Whether `value` is a 4x4 nested list of finite JSON numbers (bools and strings are not)."""
    rows = value if isinstance(value, list) and len(value) == 4 else []
    cells = [x for row in rows if isinstance(row, list) and len(row) == 4 for x in row]
    return len(cells) == 16 and all(
        isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x) for x in cells
    )


def test_mutated_frames_are_refused_with_one_line_naming_the_frame(tmp_path):
    """Any value of the wrong kind in a frame's time, pose or image path: the dataparser's check (what
    ns-train runs before its run folder) raises GaroInputError naming the file and frame, never another
    error; values that happen to be valid pass."""
    import os

    from hypothesis import HealthCheck, given, settings

    from garo_ns.data.dnerf import GaroDNeRFDataParserConfig
    from garo_ns.errors import GaroInputError

    scene = generate_scene(tmp_path / "scene", SPEC)
    original = (scene / "transforms_train.json").read_text()
    examples = int(os.environ.get("GARO_PROPERTY_EXAMPLES", "40"))

    @settings(max_examples=examples, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
    @given(mutations())
    def check(mutation: Tuple[int, str, Any]) -> None:
        i, key, value = mutation
        meta = json.loads(original)
        meta["frames"][i][key] = value
        (scene / "transforms_train.json").write_text(json.dumps(meta))
        try:
            GaroDNeRFDataParserConfig(data=scene).check_data()
        except GaroInputError as err:
            message = str(err)
            assert "\n" not in message
            assert f"{scene / 'transforms_train.json'}, frame {i}" in message, message
            return
        # Accepted: only a value valid for its field (a 4x4 matrix of finite numbers; hypothesis rarely draws one).
        assert key == "transform_matrix" and is_pose(value), (key, value)

    try:
        check()
    finally:
        (scene / "transforms_train.json").write_text(original)


def test_an_error_naming_input_with_a_newline_stays_one_line():
    """A file name with a newline (or any control character) in it is named escaped, so the error stays one line;
    a non-ASCII letter stays as it is."""
    from garo_ns.errors import GaroInputError, one_line

    err = GaroInputError("frame 0: image listed but missing: scene/a\nb\t\u00e9.png")
    assert str(err) == "frame 0: image listed but missing: scene/a\\nb\\t\u00e9.png"
    assert one_line("plain path/\u00e9t\u00e9.png") == "plain path/\u00e9t\u00e9.png"
