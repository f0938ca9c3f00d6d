"""flowins.memory: the free memory a long filter pass checks itself against."""
import torch

import flowins.memory as memory

MEMINFO = """MemTotal:       24000000 kB
MemFree:         1000000 kB
MemAvailable:    8123456 kB
Buffers:          100000 kB
"""


def test_parse_meminfo_reads_mem_available_in_bytes():
    assert memory.parse_meminfo(MEMINFO) == 8123456 * 1024
    assert memory.parse_meminfo(MEMINFO.replace("MemAvailable", "MemAvail")) is None
    assert memory.parse_meminfo("") is None


def test_available_memory_reads_the_linux_file_and_knows_no_other_device(tmp_path, monkeypatch):
    path = tmp_path / "meminfo"
    path.write_text(MEMINFO)
    monkeypatch.setattr(memory, "MEMINFO", path)
    assert memory.available_memory_bytes("cpu") == 8123456 * 1024
    monkeypatch.setattr(memory, "MEMINFO", tmp_path / "absent")
    assert memory.available_memory_bytes(torch.device("cpu")) is None
    assert memory.available_memory_bytes("meta") is None


def test_describe_bytes_switches_to_gib_at_one_gib():
    assert memory.describe_bytes(3 * 2**20) == "3 MiB"
    assert memory.describe_bytes(2**30 - 2**20) == "1023 MiB"
    assert memory.describe_bytes(2**30) == "1.0 GiB"
    assert memory.describe_bytes(7.25 * 2**30) == "7.2 GiB"
