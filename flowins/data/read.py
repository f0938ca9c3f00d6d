"""One entry point for every sequence format flowins reads: :func:`read_sequence`.

The layout of the folder decides the reader:

* flowins folder format (``imu.csv`` in the folder): :func:`flowins.data.folder.read_folder`;
* EuRoC MAV (a ``mav0/`` folder, or ``imu0/`` and ``cam0/`` in the folder itself):
  :func:`flowins.data.euroc.read_euroc`;
* ADVIO (an ``iphone/`` folder): :func:`flowins.data.advio.read_advio`;
* KITTI raw (a drive folder holding ``oxts/data/`` and ``oxts/timestamps.txt``):
  :func:`flowins.data.kitti.read_kitti_raw`.

The EuRoC, ADVIO and KITTI readers are imported only when their layout is found.
"""
from __future__ import annotations

import os
from pathlib import Path
from typing import Any

from flowins.data.sequence import Sequence

__all__ = ["detect_format", "read_sequence"]

_LOOKED_FOR = (
    "imu.csv (flowins folder format)",
    "mav0/, or imu0/ and cam0/ (EuRoC MAV)",
    "iphone/ (ADVIO)",
    "oxts/data/ and oxts/timestamps.txt (KITTI raw drive)",
)


def detect_format(path: str | os.PathLike) -> str:
    """``"flowins"``, ``"euroc"``, ``"advio"`` or ``"kitti"``: the layout of the folder ``path``.

    Raises:
        ValueError: ``path`` is not a folder, or its layout is none of the above
            (the message lists what was looked for).
    """
    folder = Path(path)
    if not folder.is_dir():
        raise ValueError(f"{folder}: not a folder; expected a sequence folder (flowins, EuRoC, ADVIO or KITTI raw layout)")
    if (folder / "imu.csv").is_file():
        return "flowins"
    if (folder / "mav0").is_dir() or ((folder / "imu0").is_dir() and (folder / "cam0").is_dir()):
        return "euroc"
    if (folder / "iphone").is_dir():
        return "advio"
    if (folder / "oxts" / "data").is_dir() and (folder / "oxts" / "timestamps.txt").is_file():
        return "kitti"
    raise ValueError(
        f"{folder}: unknown sequence layout; looked for {'; '.join(_LOOKED_FOR)} and found none"
    )


def read_sequence(path: str | os.PathLike, **kwargs: Any) -> Sequence:
    """Read the sequence in folder ``path``, whichever supported format it is in.

    ``kwargs`` go to the format's reader (e.g. ``max_imu_gap_s``, ``check_frames``
    for the flowins format, ``camera`` for EuRoC and KITTI).
    """
    kind = detect_format(path)
    if kind == "flowins":
        from flowins.data.folder import read_folder

        return read_folder(path, **kwargs)
    if kind == "euroc":
        from flowins.data.euroc import read_euroc

        return read_euroc(path, **kwargs)
    if kind == "advio":
        from flowins.data.advio import read_advio

        return read_advio(path, **kwargs)
    from flowins.data.kitti import read_kitti_raw

    return read_kitti_raw(path, **kwargs)
