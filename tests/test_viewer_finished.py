"""`ns-viewer` on a finished run shows the step it was saved at, and no button to pause a training."""

from __future__ import annotations

from types import SimpleNamespace

import garo_ns.config  # noqa: F401  (installs the plugin's nerfstudio hooks)


def _viewer_stub(trainer):
    from nerfstudio.viewer.viewer import Viewer

    stub = SimpleNamespace(
        trainer=trainer,
        step=0,
        render_statemachines={},  # no browser connected
        pause_train=SimpleNamespace(visible=True),
        resume_train=SimpleNamespace(visible=False),
        stats_markdown=SimpleNamespace(content="Step: 0  \nResolution: 0x0px"),
    )
    stub.make_stats_markdown = lambda step, res: Viewer.make_stats_markdown(stub, step, res)
    return Viewer, stub


def test_a_saved_model_shows_its_step_and_no_pause_button():
    from garo_ns import compat

    compat.install()
    viewer_cls, stub = _viewer_stub(trainer=None)
    viewer_cls.update_scene(stub, step=29_999)
    assert stub.stats_markdown.content.startswith("Step: 29999")
    assert not stub.pause_train.visible and not stub.resume_train.visible


def test_a_training_keeps_its_buttons():
    viewer_cls, stub = _viewer_stub(trainer=SimpleNamespace(training_state="training"))
    viewer_cls.update_scene(stub, step=10)
    assert stub.pause_train.visible and stub.stats_markdown.content.startswith("Step: 0")
