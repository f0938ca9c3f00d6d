"""How much memory a device has free: what a long filter pass checks itself against before it
starts (:func:`flowins.filter.runner.memory_warning`)."""
from __future__ import annotations

from pathlib import Path

import torch

MEMINFO = Path("/proc/meminfo")


def parse_meminfo(text: str) -> int | None:
    """``MemAvailable`` of a Linux ``/proc/meminfo`` text in bytes (the file gives kB), or None
    when the text has no such line."""
    for line in text.splitlines():
        name, _, rest = line.partition(":")
        if name.strip() == "MemAvailable":
            fields = rest.split()
            if fields and fields[0].isdigit():
                scale = 1024 if len(fields) < 2 or fields[1].lower() == "kb" else 1
                return int(fields[0]) * scale
    return None


def available_memory_bytes(device: torch.device | str = "cpu") -> int | None:
    """Bytes free for new tensors on ``device``: the GPU's free memory (``torch.cuda.mem_get_info``)
    or, on the CPU, the memory Linux reports available; None where it can't be told (another OS,
    another device type)."""
    device = torch.device(device)
    if device.type == "cuda":
        return int(torch.cuda.mem_get_info(device)[0])
    if device.type != "cpu":
        return None
    try:
        return parse_meminfo(MEMINFO.read_text())
    except OSError:
        return None


def describe_bytes(n: float) -> str:
    """``n`` bytes for a reader: GiB with one decimal from 1 GiB, else whole MiB."""
    return f"{n / 2**30:.1f} GiB" if n >= 2**30 else f"{n / 2**20:.0f} MiB"
