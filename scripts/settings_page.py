"""Writes docs/settings.md: every option of the plugin's methods, with its default and meaning, generated
from the config dataclasses (the docstring under each field, read as tyro reads it for `--help`).

    python scripts/settings_page.py            # rewrite docs/settings.md
    python scripts/settings_page.py --check    # exit 1 if docs/settings.md differs from what it would write
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from pathlib import Path
from typing import Any, Dict, List, Optional, Tuple

ROOT = Path(__file__).resolve().parent.parent
PAGE = ROOT / "docs" / "settings.md"

GROUPS: List[Tuple[str, str, str]] = [
    ("GaroSettings", "GARO", "garo_ns/garo_strategy.py"),
    ("CompactionSettings", "Compaction (`garo-compact`)", "garo_ns/compaction/schedule.py"),
    ("RenderSettings", "Rendering and its speed switches", "garo_ns/render/switches.py"),
    ("StaticSettings", "Static classification", "garo_ns/render/static.py"),
    ("DeformationSettings", "Deformation field", "garo_ns/deformation.py"),
    ("D3dgsRecipe", "D-3DGS recipe (splatfacto settings with D-3DGS's defaults)", "garo_ns/engine/recipe.py"),
]
"""Settings groups of GaroModelConfig: class name, heading, where it is declared."""


DATAPARSERS = {"GaroDNeRFDataParserConfig": "garo-dnerf-data", "NerfDSDataParserConfig": "nerfds-data"}
"""Dataparser config classes by the name pyproject.toml registers them under."""


def owner(cls: type, name: str) -> type:
    """The class of `cls`'s MRO that declares field `name` last (whose docstring and default apply)."""
    for klass in cls.__mro__:
        if name in klass.__dict__.get("__annotations__", {}):
            return klass
    return cls


def show(value: Any) -> str:
    """A default as it reads on the page."""
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return f"`{type(value).__name__}(...)`"
    if isinstance(value, type):
        return f"`{value.__name__}`"
    if isinstance(value, str):
        return f"`{value}`"
    return f"`{value!r}`"


def cell(text: Optional[str]) -> str:
    """A docstring as one Markdown table cell."""
    if not text:
        return "-"
    return " ".join(text.split()).replace("|", "\\|")


def field_docs(config_cls: type) -> Dict[str, Tuple[type, str, str]]:
    """Field name -> (declaring class, default shown, meaning)."""
    from tyro import _docstrings

    config = config_cls()
    out = {}
    for f in dataclasses.fields(config_cls):
        if f.name.startswith("_"):
            continue
        doc = _docstrings.get_field_docstring(config_cls, f.name, ())
        out[f.name] = (owner(config_cls, f.name), show(getattr(config, f.name)), cell(doc))
    return out


def table(rows: List[Tuple[str, str, str]]) -> List[str]:
    lines = ["| option | default | meaning |", "|---|---|---|"]
    for name, default, doc in rows:
        lines.append(f"| `{name.replace('_', '-')}` | {default} | {doc} |")
    return lines


def methods_section(config_cls: type) -> List[str]:
    """What each method sets differently from the model config's defaults, its steps and dataparser."""
    from garo_ns.config import METHODS

    base = config_cls()
    lines = [
        "## Methods",
        "",
        "Each method is the model config below with these values changed (everything else at its default):",
        "",
        "| method | steps | dataparser | model settings that differ from the defaults |",
        "|---|---|---|---|",
    ]
    for name, spec in METHODS.items():
        config = spec.config
        model = config.pipeline.model
        changed = [
            f"`{f.name.replace('_', '-')}` {show(getattr(model, f.name))}"
            for f in dataclasses.fields(config_cls)
            if not f.name.startswith("_") and getattr(model, f.name) != getattr(base, f.name)
        ]
        parser = type(config.pipeline.datamanager.dataparser).__name__
        parser = DATAPARSERS.get(parser, parser)
        lines.append(f"| `{name}` | {config.max_num_iterations:,} | `{parser}` | {', '.join(changed) or '-'} |")

    def schedules(name: str) -> dict:
        return {
            g: (e["optimizer"].lr, e.get("scheduler") and e["scheduler"].max_steps)
            for g, e in METHODS[name].config.optimizers.items()
        }

    # Read, not typed: a recipe whose rates or decay lengths differ from garo-deform's is named here.
    others = [f"`{name}`" for name in METHODS if schedules(name) != schedules("garo-deform")]
    same = "every method but " + ", ".join(others) if others else "every method, the 20k-step `-real` ones included"
    lines += [
        "",
        f"Learning rates of {same} (`--optimizers.<group>.optimizer.lr`, Adam with eps 1e-15; a schedule "
        "decays the rate exponentially to its final value over its steps, whatever the run's length, as in the "
        "official D-3DGS code):",
        "",
        "| parameter group | learning rate | final rate | decay steps |",
        "|---|---|---|---|",
    ]
    for group, entry in METHODS["garo-deform"].config.optimizers.items():
        sched = entry.get("scheduler")
        final = "-" if sched is None else f"{sched.lr_final:g}"
        steps = "-" if sched is None else f"{sched.max_steps:,}"
        lines.append(f"| `{group}` | {entry['optimizer'].lr:g} | {final} | {steps} |")
    return lines


def capture_section() -> List[str]:
    """The real-capture dataparser's options: where a user training on their own video looks."""
    from garo_ns.data.nerfds import NerfDSDataParserConfig

    return [
        "",
        "## Real captures and your own video (`nerfds-data`, the `-real` methods' dataparser)",
        "",
        "Reads a NeRF-DS / HyperNeRF capture (`dataset.json`) or a folder that `ns-process-data video` or "
        "`ns-process-data images` wrote (`transforms.json`), telling them apart itself: `ns-train garo-deform-real "
        "--data data/mine` after `ns-process-data video --data my.mp4 --output-dir data/mine` "
        "([data.md](data.md#your-own-video-ns-process-data-video-then-a--real-method)). Options go on the command line "
        "as `--pipeline.datamanager.dataparser.<option>`.",
        "",
        *table([(n, d, m) for n, (o, d, m) in field_docs(NerfDSDataParserConfig).items() if n != "data"]),
    ]


def render_page() -> str:
    from garo_ns.garo_model import GaroModelConfig

    docs = field_docs(GaroModelConfig)
    lines = [
        "# Settings",
        "",
        "<!-- Generated by `python scripts/settings_page.py` from the config dataclasses; edit the docstrings "
        "there, not this page. -->",
        "",
        "Every option of the plugin's methods with its default and meaning, read from the docstring under each "
        "field (the text `ns-train garo-deform --help` shows). Model options are set on the command line as "
        "`--pipeline.model.<option>`, e.g. `ns-train garo-deform --pipeline.model.rho-max 0.05 --data ...`.",
        "",
        *methods_section(GaroModelConfig),
        *capture_section(),
    ]
    seen = set()
    for cls_name, heading, source in GROUPS:
        rows = [(n, d, m) for n, (o, d, m) in docs.items() if o.__name__ == cls_name]
        seen.update(n for n, _, _ in rows)
        lines += ["", f"## {heading}", "", f"Declared in `{source}` (`{cls_name}`).", "", *table(rows)]
    rest = [(n, d, m) for n, (o, d, m) in docs.items() if n not in seen]
    lines += [
        "",
        "## Inherited from nerfstudio's splatfacto",
        "",
        "Declared by nerfstudio (`SplatfactoModelConfig` and its bases) and not changed by the recipe; the "
        "meaning is nerfstudio's own.",
        "",
        *table(rest),
        "",
    ]
    return "\n".join(lines)


def main(argv: Optional[List[str]] = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--check", action="store_true", help="exit 1 if the page is not up to date")
    parser.add_argument("--output", type=Path, default=PAGE)
    args = parser.parse_args(argv)
    text = render_page()
    if args.check:
        if not args.output.exists() or args.output.read_text() != text:
            print(f"{args.output} is out of date; run python scripts/settings_page.py")
            return 1
        return 0
    args.output.parent.mkdir(parents=True, exist_ok=True)
    args.output.write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
