"""Python's garbage collector paced to training: set for the run, given back after it."""

from __future__ import annotations

import gc

import pytest

from garo_ns.ops.collector import TrainingCollector, collector_paused


@pytest.fixture
def thresholds():
    saved = gc.get_threshold()
    yield saved
    gc.set_threshold(*saved)


def test_the_collector_is_paced_while_training_and_given_back_after(thresholds):
    collector = TrainingCollector(12_345)
    collector.start()
    assert gc.get_threshold() == (12_345, *thresholds[1:])
    collector.start()  # the next step's call: the thresholds saved first are kept
    collector.stop()
    assert gc.get_threshold() == thresholds
    collector.stop()  # again: nothing saved, nothing changed
    assert gc.get_threshold() == thresholds


def test_a_threshold_of_zero_leaves_the_collector_as_it_is_and_a_negative_one_is_refused(thresholds):
    off = TrainingCollector(0)
    off.start()
    assert gc.get_threshold() == thresholds and off.saved is None
    with pytest.raises(ValueError, match=">= 0"):
        TrainingCollector(-1)


def test_the_collector_is_paused_inside_and_back_as_it_was_after():
    was = gc.isenabled()
    try:
        gc.enable()
        with collector_paused():
            assert not gc.isenabled()
        assert gc.isenabled()
        with pytest.raises(RuntimeError), collector_paused():
            raise RuntimeError("a capture that fails")
        assert gc.isenabled()  # given back on an error too
        gc.disable()
        with collector_paused():
            pass
        assert not gc.isenabled()  # a collector that was off stays off
    finally:
        gc.enable() if was else gc.disable()


@pytest.mark.slow
def test_a_training_run_paces_the_collector_and_gives_it_back(tmp_path, monkeypatch, thresholds):
    from garo_ns.garo_model import GaroModel
    from garo_ns.tools.scene import SceneSpec, generate_scene
    from garo_ns.tools.train import QuickSchedule, make_config, train

    seen = []
    after = GaroModel.after_iteration

    def watched(self, step):
        seen.append(gc.get_threshold()[0])
        return after(self, step)

    monkeypatch.setattr(GaroModel, "after_iteration", watched)
    scene = generate_scene(tmp_path / "scene", SceneSpec(resolution=16, n_train=4, n_val=1, n_test=1))
    schedule = QuickSchedule(steps=20, num_random=300, deform_width=16, deform_depth=2, deform_skip=0)
    config = make_config("garo-deform", scene, tmp_path / "runs", schedule=schedule)
    config.pipeline.model.rasterizer = "reference"
    config.pipeline.model.gc_threshold = 4321
    train(config)
    assert seen and set(seen) == {4321}
    assert gc.get_threshold() == thresholds
