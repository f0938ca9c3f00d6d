"""The ``LightningModule`` that learns the filter's parameters against ground truth.

A training batch is a few sequences (``data.batch_size``). For each method (a row of
Table I) the filter runs through them window by window, the ``i``-th windows of all the
batch's sequences in one batched filter pass (:func:`flowins.training.unroll.run_windows`):
the mean of their losses is backpropagated to the windows' start and followed by one
optimiser step, and each state goes on, detached, into its sequence's next window
(truncated backpropagation through time, with Lightning's manual optimisation). Windows whose
loss or gradient is not finite are skipped and counted (``train/skipped_windows``);
the sequence's remaining windows of that method are skipped with them when the
state itself is no longer finite.

Validation runs every method over each held-out sequence in inference mode (hard
gates) and logs the filter RMSE after the Table I alignment; ``trainer.test`` prints
the held-out table of the starting, the learned and the hand-tuned parameters.
"""
from __future__ import annotations

import json
import logging
import math
from collections.abc import Mapping, Sequence
from pathlib import Path

import pytorch_lightning as pl
import torch

from flowins.navigation import NavigationConfig
from flowins.training.parameters import FilterParameters
from flowins.training.unroll import TrainingSequence, run_windows, sequence_rmse, window_bounds, window_loss

log = logging.getLogger("flowins")


class FilterLearner(pl.LightningModule):
    """Learns :class:`FilterParameters` by unrolling the filter of ``methods`` over windows.

    Args:
        params: the parameters, at their starting values.
        base: the filter configuration the parameters are written into (everything
            that is not learned: point selection, gating mode, output rate, ...).
        methods: rows of Table I to train on, e.g. ``["ins_dense", "ins_gnss_dense"]``.
        window_s: window length (s) of the truncated backpropagation.
        nll_weight: weight of the Gaussian negative log-likelihood in the loss.
        orientation_weight_m_per_rad: weight of the orientation RMSE (rad) in the loss
            (metres per radian; 0: position only).
        lr, gradient_clip: Adam's learning rate (in log-parameter units) and the
            gradient-norm clip of each step.
        reference: named parameter values the held-out test compares with (e.g. the
            starting values and the hand-tuned defaults).
    """

    def __init__(
        self,
        params: FilterParameters,
        base: NavigationConfig,
        *,
        methods: Sequence[str],
        window_s: float = 20.0,
        nll_weight: float = 0.0,
        orientation_weight_m_per_rad: float = 0.0,
        lr: float = 0.1,
        gradient_clip: float = 1.0,
        reference: Mapping[str, Mapping[str, float]] | None = None,
        output_dir: str | None = None,
    ) -> None:
        super().__init__()
        self.automatic_optimization = False
        self.params = params
        self.base = base
        self.methods = list(methods)
        self.window_s = float(window_s)
        self.nll_weight = float(nll_weight)
        self.orientation_weight = float(orientation_weight_m_per_rad)
        self.lr = float(lr)
        self.gradient_clip = float(gradient_clip)
        self.reference = {k: dict(v) for k, v in (reference or {}).items()}
        self.output_dir = output_dir
        self.skipped_windows = 0
        self.trained_windows = 0
        self._heldout: dict[str, dict[str, list[float]]] = {}
        self.save_hyperparameters({"methods": self.methods, "window_s": self.window_s, "nll_weight": self.nll_weight,
                                   "orientation_weight_m_per_rad": self.orientation_weight,
                                   "lr": self.lr, "gradient_clip": self.gradient_clip, "reference": self.reference,
                                   "learned": params.learned})

    def configure_optimizers(self):
        learned = [p for p in self.params.parameters() if p.requires_grad]
        if not learned:
            raise ValueError("model: every parameter is frozen; nothing to learn")
        return torch.optim.Adam(learned, lr=self.lr)

    # ------------------------------------------------------------------ training
    def training_step(self, batch: TrainingSequence | list[TrainingSequence], batch_idx: int) -> None:
        opt = self.optimizers()
        seqs = batch if isinstance(batch, list) else [batch]
        bounds = [window_bounds(seq.imu.t_s, self.window_s) for seq in seqs]
        for method in self.methods:
            starts: list = [None] * len(seqs)
            going = [True] * len(seqs)  # a sequence whose state stopped being finite leaves the batch
            for i in range(max(len(b) for b in bounds)):
                rows = [k for k in range(len(seqs)) if going[k] and i < len(bounds[k])]
                if not rows:
                    break
                config = self.params.apply(self.base, training=True)
                moments = _has_moments(seqs[rows[0]], method)
                p = self.params.value("dropout_p") if moments else None
                results = run_windows([seqs[k] for k in rows], method, config, [bounds[k][i] for k in rows],
                                      dropout_p=p, starts=[starts[k] for k in rows])
                losses = []
                for k, result in zip(rows, results):
                    loss = window_loss(result.track, seqs[k].truth, nll_weight=self.nll_weight,
                                       orientation_weight_m_per_rad=self.orientation_weight)
                    state_ok = bool(torch.isfinite(result.mean).all() and torch.isfinite(result.cov).all())
                    if bool(torch.isfinite(loss.loss)):
                        losses.append(loss)
                    else:
                        self._skip(1 if state_ok else len(bounds[k]) - i)
                    if state_ok:
                        starts[k] = (result.mean.detach(), result.cov.detach())
                    else:
                        going[k] = False
                        if bool(torch.isfinite(loss.loss)):
                            self._skip(len(bounds[k]) - i - 1)
                if not losses:
                    continue
                # one optimiser step on the mean loss of the batch's windows
                total = torch.stack([w.loss for w in losses]).mean()
                opt.zero_grad()
                self.manual_backward(total)
                grads = [q.grad for q in self.params.parameters() if q.grad is not None]
                if not all(bool(torch.isfinite(g).all()) for g in grads):
                    opt.zero_grad()
                    self._skip(len(losses))
                else:
                    self.clip_gradients(opt, gradient_clip_val=self.gradient_clip, gradient_clip_algorithm="norm")
                    opt.step()
                    self.trained_windows += len(losses)
                n = len(losses)
                self.log(f"train/{method}/rmse_m", torch.stack([w.rmse_m for w in losses]).mean(), on_step=True,
                         batch_size=n)
                self.log("train/loss", total.detach(), on_step=True, prog_bar=True, batch_size=n)
                if self.nll_weight > 0:
                    self.log("train/nll", torch.stack([w.nll for w in losses]).mean(), on_step=True, batch_size=n)
                if self.orientation_weight > 0:
                    self.log(f"train/{method}/orientation_rmse_rad",
                             torch.stack([w.orientation_rmse_rad for w in losses]).mean(), on_step=True, batch_size=n)
                for name, value in self.params.values().items():
                    if self.params.raw[name].requires_grad:
                        self.log(f"params/{name}", value, on_step=True, batch_size=n)
        self.log("train/skipped_windows", float(self.skipped_windows), on_step=True, batch_size=1)

    def _skip(self, n: int) -> None:
        self.skipped_windows += n

    # ------------------------------------------------------------------ held-out
    def _rmse(self, seq: TrainingSequence, method: str, params: FilterParameters) -> float:
        p = float(params.value("dropout_p").detach()) if _has_moments(seq, method) else None
        return sequence_rmse(seq, method, params.apply(self.base, training=False), dropout_p=p)

    def validation_step(self, batch: TrainingSequence, batch_idx: int) -> None:
        values = []
        for method in self.methods:
            rmse = self._rmse(batch, method, self.params)
            self.log(f"val/{method}/filter_rmse_m", rmse, on_epoch=True, batch_size=1)
            values.append(rmse if math.isfinite(rmse) else 1e6)
        self.log("val/rmse_mean_m", sum(values) / len(values), on_epoch=True, prog_bar=True, batch_size=1)

    def test_step(self, batch: TrainingSequence, batch_idx: int) -> None:
        candidates = {"learned": self.params}
        for name, values in self.reference.items():
            candidates[name] = FilterParameters(values, learn=())
        for label, params in candidates.items():
            for method in self.methods:
                rmse = self._rmse(batch, method, params)
                self._heldout.setdefault(label, {}).setdefault(method, []).append(rmse)
                self.log(f"test/{label}/{method}/filter_rmse_m", rmse, on_epoch=True, batch_size=1)

    def on_test_epoch_end(self) -> None:
        table = heldout_table(self._heldout, self.methods)
        log.info("\nheld-out filter RMSE (m, Table I alignment), mean over the held-out sequences\n")
        log.info(table)
        if self.output_dir:
            out = Path(self.output_dir)
            out.mkdir(parents=True, exist_ok=True)
            (out / "heldout.json").write_text(json.dumps(
                {"rmse_m": self._heldout, "learned_values": self.params.values(), "reference": self.reference},
                indent=2))
            (out / "heldout.txt").write_text(table + "\n")


def _has_moments(seq: TrainingSequence, method: str) -> bool:
    _, flow = seq.sources(method)
    return flow is not None and bool(flow.points) and flow.points[0].dropout_unit_px is not None


def heldout_table(results: Mapping[str, Mapping[str, list[float]]], methods: Sequence[str]) -> str:
    """Fixed-width table: one row per parameter set, one column per method (mean RMSE)."""
    lines = [f"{'parameters':<14}" + "".join(f"{m:>18}" for m in methods)]
    for label, per_method in results.items():
        cells = []
        for m in methods:
            v = per_method.get(m, [])
            cells.append(f"{sum(v) / len(v):>16.2f} m" if v else f"{'n/a':>18}")
        lines.append(f"{label:<14}" + "".join(cells))
    if "start" in results and "learned" in results:
        change = []
        for m in methods:
            a, b = results["start"].get(m), results["learned"].get(m)
            change.append(f"{100 * (1 - (sum(b) / len(b)) / (sum(a) / len(a))):>16.1f} %" if a and b else f"{'':>18}")
        lines.append(f"{'reduction':<14}" + "".join(change))
    return "\n".join(lines)
