"""The learning-rate schedule and the window curriculum, against their defining properties."""
import pytest

from flowins.training.schedule import learning_rate, window_length


def test_the_warm_up_is_linear_from_a_tenth_and_reaches_the_rate_at_its_last_step():
    rates = [learning_rate(s, 0, lr=0.2, lr_final=0.02, warmup_steps=4, epochs=3) for s in range(8)]
    # first step: a tenth of the way up from lr/10
    assert rates[0] == pytest.approx(0.02 + 0.18 * 0.25)
    steps = [b - a for a, b in zip(rates, rates[1:4])]
    assert steps == pytest.approx([steps[0]] * 3)  # equal increments: linear
    assert rates[3:] == pytest.approx([0.2] * 5)  # at lr from the warm-up's last step on (epoch 0: no decay yet)
    assert learning_rate(0, 0, lr=0.2, lr_final=0.02, warmup_steps=0, epochs=3) == 0.2


def test_the_decay_runs_from_the_rate_to_the_final_rate_over_the_epochs_as_half_a_cosine():
    epochs = 5
    rates = [learning_rate(100, e, lr=0.1, lr_final=0.01, warmup_steps=5, epochs=epochs) for e in range(epochs)]
    assert rates[0] == pytest.approx(0.1)
    assert rates[-1] == pytest.approx(0.01)
    assert rates[2] == pytest.approx(0.055)  # the midpoint of a cosine half-period is the mean
    assert rates[1] - rates[2] == pytest.approx(rates[2] - rates[3])  # symmetric about the midpoint
    assert all(b < a for a, b in zip(rates, rates[1:]))
    # beyond the last epoch (a resumed run) the rate stays at its final value
    assert learning_rate(100, 9, lr=0.1, lr_final=0.01, warmup_steps=5, epochs=epochs) == pytest.approx(0.01)
    # one epoch, or no limit on epochs: no decay
    assert learning_rate(100, 0, lr=0.1, lr_final=0.01, warmup_steps=5, epochs=1) == 0.1
    assert learning_rate(100, 7, lr=0.1, lr_final=0.01, warmup_steps=5, epochs=None) == 0.1
    with pytest.raises(ValueError, match="step and epoch"):
        learning_rate(-1, 0, lr=0.1, lr_final=0.01, warmup_steps=5, epochs=3)


def test_the_curriculum_gives_its_windows_first_then_the_window():
    assert [window_length(e, window_s=20.0, curriculum=[5.0, 10.0]) for e in range(4)] == [5.0, 10.0, 20.0, 20.0]
    assert window_length(0, window_s=20.0) == 20.0
