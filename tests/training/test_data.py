"""flowins.training.data: the order of the training sequences."""
import torch

from flowins.training.data import SequenceDataModule


def _order(module: SequenceDataModule, epochs: int, draw_between: int) -> list[list[int]]:
    """The sequences' order in each of ``epochs`` passes over the training loader, with
    ``draw_between`` draws from torch's global generator before each pass (what a validation
    or a long held-out walk may take)."""
    loader = module.train_dataloader()
    orders = []
    for _ in range(epochs):
        torch.rand(draw_between)
        orders.append([batch[0] for batch in loader])
    return orders


def test_the_training_order_depends_on_the_seed_alone():
    """The same seed gives the same order whatever else draws from torch's global generator
    (a run with data.select validates more than one without it); the order is shuffled, and
    another seed gives another."""
    def module(seed: int) -> SequenceDataModule:
        m = SequenceDataModule(train=[{"seed": k} for k in range(8)], val=[{"seed": 9}], config={}, methods=["ins"],
                               seed=seed)
        m.sequences["train"] = list(range(8))  # stand-ins: the loader only orders them
        return m

    torch.manual_seed(0)
    plain = _order(module(0), epochs=3, draw_between=0)
    torch.manual_seed(0)
    busy = _order(module(0), epochs=3, draw_between=1000)
    assert plain == busy
    assert len({tuple(o) for o in plain}) == 3 and all(sorted(o) == list(range(8)) for o in plain)
    assert _order(module(1), epochs=3, draw_between=0) != plain
