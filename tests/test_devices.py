"""The fake device of ``conftest.FakeDevice``: the CPU stand-in for a GPU that the filter's
device tests run on. It must see the slips a GPU would raise on, and nothing else."""
import numpy as np
import torch

FAKE = torch.device("meta")


def test_the_fake_device_records_a_cpu_tensor_meeting_a_device_tensor_and_a_numpy_of_one(fake_device):
    with fake_device() as mode:
        x = torch.ones(3, dtype=torch.float64, device=FAKE)
        assert x.device == FAKE and (x + 1).device == FAKE and x.new_zeros(2).device == FAKE
        _ = x * torch.ones(3, dtype=torch.float64)  # a CPU constant: a GPU raises here
        _ = torch.stack((x, torch.zeros(3, dtype=torch.float64)))
        _ = np.asarray(x.numpy())
        _ = torch.arange(3.0)[torch.tensor([0, 2], device=FAKE)]  # CPU values, device indices: a GPU raises
    assert len(mode.slips) == 4, mode.slips
    assert any(key.startswith("__getitem__: a CPU tensor (3,) indexed") for key in mode.slips)
    assert any(key.startswith("mul: 1 CPU tensor(s) [(3,)]") for key in mode.slips)
    assert any(key.startswith("numpy()") for key in mode.slips)


def test_the_fake_device_lets_through_what_a_gpu_allows(fake_device):
    """Moves both ways, allocations that follow the device, 0-dim CPU scalars, assignment of a
    CPU value and indexing with CPU indices; the values are the CPU's."""
    with fake_device() as mode:
        cpu = torch.arange(4, dtype=torch.float64)
        x = cpu.to(FAKE)
        y = x * torch.tensor(2.0, dtype=torch.float64) + torch.eye(4, dtype=x.dtype, device=x.device)[0]
        y[0] = torch.tensor([7.0], dtype=torch.float64)
        z = y[torch.tensor([0, 2])] + torch.zeros_like(y)[:2]
        back = z.cpu()
        assert z.device == FAKE and back.device == torch.device("cpu") and cpu.to(x).device == FAKE
        assert back.to(x.device).device == FAKE and x.to("cpu").device == torch.device("cpu")
    assert mode.slips == {}
    assert back.tolist() == [7.0, 4.0]


def test_the_fake_device_records_each_read_of_a_device_tensor_by_the_host(fake_device):
    """``tolist``, ``item``, ``bool``, ``float``, ``nonzero`` and a move to the CPU of a tensor on
    the device are reads (on a GPU each waits for its queue); the same calls on CPU tensors and
    ops that keep their results on the device are not."""
    with fake_device() as mode:
        x = torch.arange(4.0, dtype=torch.float64, device=FAKE)
        _ = (x * 2).any(), x.sum(), x[torch.tensor([1, 2])]  # no read
        _ = torch.arange(3.0).tolist(), float(torch.ones(()))  # CPU tensors: no read
        _ = x.tolist(), x[0].item(), bool(x.any()), float(x.sum()), torch.nonzero(x), x.cpu()
    names = sorted(key.split(" at ")[0] for key in mode.reads)
    assert names == ["__bool__", "__float__", "cpu", "item", "nonzero", "tolist"], mode.reads
    assert mode.copies == {}, mode.copies  # arange made on the device copies no host data


def test_the_fake_device_records_each_copy_of_host_data_to_it(fake_device):
    """``to`` of a CPU tensor and ``tensor`` / ``as_tensor`` made on the device copy host data
    there; allocations on it, moves of its own tensors and moves back are no copies."""
    with fake_device() as mode:
        x = torch.zeros(3, dtype=torch.float64, device=FAKE)  # an allocation
        _ = x.to(torch.float32), torch.as_tensor(x, device=FAKE), x.cpu()  # no host data moved
        _ = torch.ones(2).to(FAKE), torch.ones(2).to(x), torch.tensor([1, 2], device=FAKE)
        _ = torch.as_tensor([0.5], device=x.device)
    names = sorted(key.split(" at ")[0] for key in mode.copies)
    assert names == ["as_tensor", "tensor", "to"] and sum(mode.copies.values()) == 4, mode.copies
