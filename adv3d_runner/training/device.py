"""Where a model trains: ``--device cpu|cuda|auto`` of every ``adv3d train`` command.

``cpu`` (the default) is what the shipped weights were trained on: with one torch thread and
the same seed it gives the same weights, byte for byte. ``cuda`` trains on the first GPU
(faster, but not bit-reproducible against the CPU: cuDNN picks its own kernels); ``auto`` picks
``cuda`` when a GPU is visible, else ``cpu``.
"""
from __future__ import annotations

DEVICES = ("cpu", "cuda", "auto")


def resolve_device(name: str):
    """The ``torch.device`` for ``--device name``.

    Raises:
        ConfigError: an unknown name, or ``cuda`` without a visible GPU.
    """
    import torch

    from ..errors import ConfigError

    name = str(name).lower()
    if name not in DEVICES:
        raise ConfigError(f"--device must be one of {', '.join(DEVICES)}, got {name!r}")
    if name == "auto":
        name = "cuda" if torch.cuda.is_available() else "cpu"
    if name == "cuda" and not torch.cuda.is_available():
        raise ConfigError("--device cuda: no GPU is visible to torch (use --device cpu or auto)")
    return torch.device(name)


def device_info(device) -> dict:
    """What the training report records about the device."""
    import torch

    info = {"device": str(device)}
    if getattr(device, "type", str(device)) == "cuda":
        info["gpu"] = torch.cuda.get_device_name(device)
    return info
