"""Training's allocator setting (garo_ns.engine.allocator): applied on CUDA only, never over the user's own."""

import torch

from garo_ns.config import deform_splatfacto, deform_splatfacto_real, garo_compact_real, garo_deform_real
from garo_ns.engine import allocator


def _calls(monkeypatch):
    calls = []
    monkeypatch.setattr(torch.cuda.memory, "_set_allocator_settings", calls.append)
    for name in allocator.SETTING_VARIABLES:
        monkeypatch.delenv(name, raising=False)
    return calls


def test_cuda_training_grows_segments_in_place(monkeypatch):
    calls = _calls(monkeypatch)
    assert allocator.extend_segments_in_place("cuda:0") is True
    assert calls == ["expandable_segments:True"]


def test_nothing_changes_off_cuda_or_over_the_users_setting(monkeypatch):
    calls = _calls(monkeypatch)
    assert allocator.extend_segments_in_place("cpu") is False
    for name in allocator.SETTING_VARIABLES:
        monkeypatch.setenv(name, "max_split_size_mb:128")
        assert allocator.extend_segments_in_place(torch.device("cuda")) is False
        monkeypatch.delenv(name)
    assert calls == []


def test_the_real_recipes_use_it_and_the_dnerf_one_does_not():
    for spec in (garo_deform_real, deform_splatfacto_real, garo_compact_real):
        assert spec.config.pipeline.model.expandable_segments is True
    assert deform_splatfacto.config.pipeline.model.expandable_segments is False


def test_training_callbacks_apply_it_for_the_models_device(monkeypatch):
    from types import SimpleNamespace

    from garo_ns.engine import callbacks

    seen = []
    monkeypatch.setattr(callbacks, "extend_segments_in_place", seen.append)

    class Stop(Exception):
        pass

    def adopt(pipeline):
        raise Stop  # the rest of the set-up is other tests' business

    for on in (True, False):
        model = SimpleNamespace(
            config=SimpleNamespace(expandable_segments=on), device="cuda", adopt_training_data=adopt
        )
        try:
            callbacks.training_callbacks(model, SimpleNamespace(pipeline=None))
        except Stop:
            pass
    assert seen == ["cuda"]
