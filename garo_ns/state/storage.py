"""Compact storage of a trained model: what rendering needs, in half precision.

A trained model is its Gaussians plus the deformation MLP. Positions stay float32 (in float16 a
lego-sized scene would move by up to a third of a pixel at 800 px); everything else (scales,
rotations, opacities, SH coefficients, MLP weights) is stored as float16, whose 11-bit
significand is finer than any of them is learnt to. `load_compact` puts the rounded values back
into a model as float32, so what renders after loading is exactly what the file holds.
"""

from __future__ import annotations

import io
from pathlib import Path
from typing import Any, Dict, Union

import torch
from torch import Tensor

FULL_PRECISION = ("gauss_params.means",)


def compact_state(model: Any) -> Dict[str, Tensor]:
    """Gaussians and deformation MLP of `model`, positions in float32 and the rest in float16."""
    state: Dict[str, Tensor] = {}
    named = [(f"gauss_params.{k}", v) for k, v in model.gauss_params.items()]
    named += [(f"deformation.{k}", v) for k, v in model.deformation.named_parameters()]
    for name, tensor in named:
        tensor = tensor.detach().cpu()
        if not bool(torch.isfinite(tensor).all()):
            raise ValueError(f"{name} holds non-finite values; refusing to store a broken model")
        if name not in FULL_PRECISION:
            if tensor.numel() and float(tensor.abs().amax()) > torch.finfo(torch.float16).max:
                raise ValueError(f"{name} exceeds the float16 range; store it in full precision")
            tensor = tensor.half()
        state[name] = tensor
    return state


def compact_bytes(model: Any) -> bytes:
    """The compact file's contents (torch.save of `compact_state`)."""
    buffer = io.BytesIO()
    torch.save(compact_state(model), buffer)
    return buffer.getvalue()


def save_compact(model: Any, path: Union[str, Path]) -> int:
    """Write the compact file; returns its size in bytes."""
    data = compact_bytes(model)
    Path(path).write_bytes(data)
    return len(data)


@torch.no_grad()
def load_compact(model: Any, source: Union[str, Path, bytes]) -> None:
    """Load a compact file into `model` in place (float32 parameters, same Parameter objects).

    The model must have the same number of Gaussians and the same MLP shape as the file.
    """
    raw = source if isinstance(source, bytes) else Path(source).read_bytes()
    state = torch.load(io.BytesIO(raw), map_location="cpu", weights_only=True)
    params: Dict[str, Tensor] = {f"gauss_params.{k}": v for k, v in model.gauss_params.items()}
    params.update({f"deformation.{k}": v for k, v in model.deformation.named_parameters()})
    missing = sorted(set(params) - set(state))
    if missing:
        raise ValueError(f"compact file lacks {missing}")
    for name, value in state.items():  # check everything before changing anything
        target = params.get(name)
        if target is None:
            raise ValueError(f"compact file holds {name}, which the model does not have")
        if tuple(target.shape) != tuple(value.shape):
            raise ValueError(f"{name}: file shape {tuple(value.shape)} != model shape {tuple(target.shape)}")
        if not bool(torch.isfinite(value).all()):
            raise ValueError(f"{name} holds non-finite values in the compact file")
    for name, value in state.items():
        params[name].copy_(value.to(params[name].dtype))
    _values_replaced(model)


def _values_replaced(model: Any) -> None:
    """Tell the model's render switches that the values they were measured on are gone (a record of the fp32
    values does not describe the rounded ones)."""
    switches = getattr(model, "switches", None)
    if switches is not None:
        switches.parameters_changed()


def round_to_storage(model: Any) -> int:
    """Replace the model's parameters by what its compact file holds; returns the file's bytes."""
    data = compact_bytes(model)
    load_compact(model, data)
    return len(data)


def snapshot(model: Any) -> Dict[str, Tensor]:
    """Copies of every stored parameter, to undo `round_to_storage` (see `restore`)."""
    out = {f"g.{k}": v.detach().clone() for k, v in model.gauss_params.items()}
    out.update({f"d.{k}": v.detach().clone() for k, v in model.deformation.named_parameters()})
    return out


@torch.no_grad()
def restore(model: Any, saved: Dict[str, Tensor]) -> None:
    """Put back the parameters saved by `snapshot`."""
    for k, v in model.gauss_params.items():
        v.copy_(saved[f"g.{k}"])
    for k, v in model.deformation.named_parameters():
        v.copy_(saved[f"d.{k}"])
    _values_replaced(model)
