"""The ``LightningModule`` that learns the filter's parameters against ground truth.

A training batch is a few sequences (``data.batch_size``), each run under every method (a
row of Table I): the filter runs through them window by window, the ``i``-th windows of all
the batch's sequences under all methods in one batched filter pass
(:func:`flowins.training.unroll.run_windows`), and each state goes on, detached, into its
row's next window (truncated backpropagation through time, with Lightning's manual
optimisation). The gradients of
``model.accumulate_windows`` such window groups are summed, and one Adam step is taken on
their mean: the mean over every window of every process, so that two processes (DDP)
step exactly as one process with both processes' sequences would. The learning rate
follows :func:`flowins.training.schedule.learning_rate` (warm-up, then a cosine decay over
the epochs) and the window length :func:`~flowins.training.schedule.window_length` (a
curriculum of short windows first). Windows whose loss or gradient is not finite are
skipped and counted (``train/skipped_windows``); the row's remaining windows are skipped
with them when the state itself is no longer finite.

Validation runs every method over each held-out sequence in inference mode (hard
gates) and logs the filter RMSE after the Table I alignment. Each validation is kept in
:attr:`FilterLearner.history` with the parameters it scored; the training job validates
the start before the first step, and :meth:`FilterLearner.select_best` takes the best of
the start and every epoch. With long held-out sequences ``data.select``
(:attr:`~flowins.training.data.SequenceDataModule.select_sequences`), each validation also
runs every method over all of them (one batched filter pass), and the best
validation is the one with the lowest mean RMSE over those sequences and methods, not the
``data.val`` score: parameters that fit short windows best may drift most over long walks.
``trainer.test`` prints the held-out table of the starting, the learned (selected) and the
hand-tuned parameters, with the ``select`` sequences' mean ± std beside the ``val`` means.
"""
from __future__ import annotations

import json
import logging
import math
import time
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path

import pytorch_lightning as pl
import torch
from pytorch_lightning.trainer.states import TrainerFn

from flowins.batching import run_load
from flowins.filter.ekf import chi2_quantile
from flowins.navigation import NavigationConfig
from flowins.parallel import in_distributed_run, split_by_load
from flowins.training.parameters import FilterParameters, ModelSettings
from flowins.training.schedule import learning_rate, window_length
from flowins.training.unroll import (
    METHODS,
    TrainingSequence,
    has_moments,
    run_windows,
    sequence_load,
    sequences_errors,
    split_gradient,
    window_bounds,
    window_loss,
)

log = logging.getLogger("flowins")


class FilterLearner(pl.LightningModule):
    """Learns :class:`FilterParameters` by unrolling the filter of ``methods`` over windows.

    Args:
        params: the parameters, at their starting values.
        base: the filter configuration the parameters are written into (everything
            that is not learned: point selection, gating mode, output rate, ...).
        methods: rows of Table I to train on, e.g. ``["ins_dense", "ins_gnss_dense"]``.
        model: the loss and the optimiser's schedule (:class:`ModelSettings`).
        window_s: window length (s) of the truncated backpropagation.
        curriculum_window_s: the first epochs' shorter windows (s).
        reference: named parameter values the held-out test compares with (e.g. the
            starting values and the hand-tuned defaults).
    """

    def __init__(
        self,
        params: FilterParameters,
        base: NavigationConfig,
        *,
        methods: Sequence[str],
        model: ModelSettings = ModelSettings(),
        window_s: float = 20.0,
        curriculum_window_s: Sequence[float] = (),
        reference: Mapping[str, Mapping[str, float]] | None = None,
        output_dir: str | None = None,
    ) -> None:
        super().__init__()
        self.automatic_optimization = False
        self.params = params
        self.base = base
        self.methods = list(methods)
        self.window_s = float(window_s)
        self.curriculum = [float(w) for w in curriculum_window_s]
        self.nll_weight = model.nll_weight
        self.orientation_weight = model.orientation_weight_m_per_rad
        self.innovation_weight = model.innovation_weight
        self.innovation_learns = frozenset(model.innovation_learns)
        self.noise_level = model.noise_level
        self.level_names = model.level_group(params.learned)
        self.loss = model.loss
        self.segment_s = tuple(model.segment_s)
        self.lr = model.lr
        self.adaptive_lr = model.adaptive_lr
        self.lr_final = self.lr if model.lr_final is None else model.lr_final
        self.warmup_steps = model.warmup_steps
        self.accumulate = model.accumulate_windows
        self.average_epochs = model.average_epochs
        self.select_flow_gate = tuple(model.select_flow_gate)
        self.recheck_while_training = model.recheck_while_training
        if self.select_flow_gate and not any(METHODS.get(m, (False, False, False))[2] for m in self.methods):
            raise ValueError(f"model.select_flow_gate: no method of {self.methods} uses dense flow, whose gate it "
                             "chooses; leave it empty or add a method with dense flow")
        #: the running sum of the learned tensors after each step of the averaged epochs, and their count
        self._sums: dict[str, torch.Tensor] = {}
        self._summed = 0
        self._next_label: str | None = None  # the label of the next validation outside fit (use_average)
        self.gradient_clip = model.gradient_clip
        self.reference = {k: dict(v) for k, v in (reference or {}).items()}
        self.output_dir = output_dir
        self.skipped_windows = 0
        self.trained_windows = 0
        self.optimizer_steps = 0
        #: every held-out validation: {"label", "step", "rmse_m" {method: mean}, "score",
        #: "raw" {name: the optimiser's coordinate}, "values" {name: value}},
        #: with ``data.select`` also "select_rmse_m" {method: [RMSE of each select sequence]} and "select_score"
        self.history: list[dict] = []
        #: each validation's adaptive noise weights by its label (restored with its ``raw``)
        self._adaptive_states: dict[str, dict] = {}
        self._val: dict[str, list[float]] = {}
        self._first_validation: float | None = None  # time.monotonic() of the first, for the log lines
        self._heldout: dict[str, dict[str, list[float]]] = {}
        self._heldout_select: dict[str, dict[str, list[float]]] = {}
        self._heldout_select_smoother: dict[str, dict[str, list[float]]] = {}
        self.save_hyperparameters({"methods": self.methods, "window_s": self.window_s,
                                   "curriculum_window_s": self.curriculum, "nll_weight": self.nll_weight,
                                   "orientation_weight_m_per_rad": self.orientation_weight,
                                   "innovation_weight": self.innovation_weight,
                                   "innovation_learns": sorted(self.innovation_learns),
                                   "noise_level": self.noise_level, "loss": self.loss,
                                   "segment_s": list(self.segment_s), "lr": self.lr, "adaptive_lr": self.adaptive_lr,
                                   "lr_final": self.lr_final, "warmup_steps": self.warmup_steps,
                                   "accumulate_windows": self.accumulate, "average_epochs": self.average_epochs,
                                   "gradient_clip": self.gradient_clip,
                                   "recheck_while_training": self.recheck_while_training,
                                   "reference": self.reference, "learned": params.learned})

    def configure_optimizers(self):
        networks = {id(p) for p in self.params.adaptive.parameters()}
        learned = [p for p in self.params.parameters() if p.requires_grad and id(p) not in networks]
        weights = [p for p in self.params.adaptive.parameters() if p.requires_grad]
        if not learned and not weights:
            raise ValueError("model: every parameter is frozen; nothing to learn")
        # the networks' weights on the same schedule at their own rate: a step of lr = 0.2 in
        # every weight at once saturates the networks' outputs at their bounds
        groups = [{"params": learned, "scale": 1.0}] if learned else []
        groups += [{"params": weights, "scale": self.adaptive_lr / self.lr}] if weights else []
        return torch.optim.Adam(groups, lr=self.lr)

    # ------------------------------------------------------------------ training
    def training_step(self, batch: TrainingSequence | list[TrainingSequence], batch_idx: int) -> None:
        opt = self.optimizers()
        seqs = batch if isinstance(batch, list) else [batch]
        window = window_length(self.current_epoch, window_s=self.window_s, curriculum=self.curriculum)
        bounds = [window_bounds(seq.imu.t_s, window) for seq in seqs]
        named = list(self._learned_tensors().items())
        learned = [q for _, q in named]
        from_likelihood = [n in self.innovation_learns for n, _ in named]
        level = [n in self.level_names for n, _ in named] if self.level_names else None
        # one row per sequence and method: the i-th windows of all of them run as one batched filter
        pairs = [(k, method) for method in self.methods for k in range(len(seqs))]
        starts: list = [None] * len(pairs)
        aligned: list = [None] * len(pairs)  # model.loss=start: each row's one alignment
        going = [True] * len(pairs)  # a row whose state stopped being finite leaves the batch
        # every process takes the same number of steps (their batches may differ in windows)
        f64 = {"dtype": torch.float64, "device": self.device}  # NCCL reduces tensors on the GPU
        count = int(self._sum_over_processes(torch.tensor([max(len(b) for b in bounds)], **f64), reduce="max")[0])
        gradient, present, pending = self._no_gradient(learned), torch.zeros(len(learned), **f64), 0
        for i in range(count):
            rows = [r for r, (k, _) in enumerate(pairs) if going[r] and i < len(bounds[k])]
            losses = self._window_losses(seqs, pairs, rows, starts, going, bounds, i, aligned)
            if losses:
                total = torch.stack([w.loss for _, w, _ in losses]).sum()
                parts = [x for _, _, x in losses if x is not None]
                likelihood = torch.stack(parts).sum() if parts else None
                grads = split_gradient(total, likelihood, learned, from_likelihood, level)
                flat = torch.cat([q.new_zeros(q.numel()) if g is None else g.reshape(-1)
                                  for q, g in zip(learned, grads)])
                if bool(torch.isfinite(flat).all()):
                    gradient += flat
                    present += torch.tensor([float(g is not None) for g in grads], **f64)
                    pending += len(losses)
                else:
                    self._skip(len(losses))
                self._log_windows(total.detach() / len(losses), losses)
            if (i + 1) % self.accumulate == 0 or i == count - 1:
                self._step(opt, learned, gradient, present, pending)
                gradient, present, pending = self._no_gradient(learned), torch.zeros_like(present), 0
        self.log("train/skipped_windows", float(self.skipped_windows), on_step=True, batch_size=1)

    def _window_losses(self, seqs, pairs, rows, starts, going, bounds, i, aligned) -> list:
        """``[(method, loss, likelihood)]`` of the rows' ``i``-th windows (``likelihood``: the
        innovation negative log-likelihood per scalar measurement with its graph where
        ``model.innovation_learns`` names parameters, else None) (row ``r`` is sequence
        ``pairs[r][0]`` under method ``pairs[r][1]``; one batched filter pass); the rows'
        states go on, detached, to their next windows (with ``model.loss=start``, their first
        window's alignment too, in ``aligned``), and a row whose state is not finite leaves
        the batch (its remaining windows counted as skipped)."""
        if not rows:
            return []
        config = self.filter_config(self.params, training=True)
        moments = any(_has_moments(seqs[pairs[r][0]], pairs[r][1]) for r in rows)
        p = self.params.value("dropout_p") if moments else None
        results = run_windows([seqs[pairs[r][0]] for r in rows], [pairs[r][1] for r in rows], config,
                              [bounds[pairs[r][0]][i] for r in rows], dropout_p=p, starts=[starts[r] for r in rows],
                              likelihood=self.innovation_weight > 0 or self._per_measurement)
        losses = []
        for r, result in zip(rows, results):
            k, method = pairs[r]
            loss = window_loss(result.track, seqs[k].truth, nll_weight=self.nll_weight,
                               orientation_weight_m_per_rad=self.orientation_weight,
                               innovation_weight=self.innovation_weight, innovation=(result.nll, result.nll_count),
                               loss=self.loss, segment_s=self.segment_s, alignment=aligned[r])
            if self.loss == "start" and aligned[r] is None:
                aligned[r] = loss.alignment
            state_ok = bool(torch.isfinite(result.mean).all() and torch.isfinite(result.cov).all())
            finite = bool(torch.isfinite(loss.loss))
            # the innovation likelihood per scalar measurement, with its graph (model.innovation_learns)
            per_measurement = (result.nll / max(result.nll_count, 1.0) if self._per_measurement and result.nll is not None
                               else None)
            finite = finite and (per_measurement is None or bool(torch.isfinite(per_measurement)))
            if finite:
                losses.append((method, loss, per_measurement))
            if state_ok:
                starts[r] = (result.mean.detach(), result.cov.detach())
            else:
                going[r] = False
            self._skip((0 if finite else 1) + (0 if state_ok else len(bounds[k]) - i - 1))
        return losses

    @property
    def _per_measurement(self) -> bool:
        """Whether a window's innovation likelihood per scalar measurement has its own gradient
        (``model.innovation_learns``, ``model.noise_level=likelihood``)."""
        return bool(self.innovation_learns or self.level_names)

    def _no_gradient(self, learned: list[torch.Tensor]) -> torch.Tensor:
        return torch.zeros(sum(q.numel() for q in learned), dtype=torch.float64, device=self.device)

    def _step(self, opt, learned: list[torch.Tensor], gradient: torch.Tensor, present: torch.Tensor,
              pending: int) -> None:
        """One Adam step on the mean gradient of the ``pending`` windows behind ``gradient`` (their
        sum), over all processes; nothing when no process has a window. A parameter no window
        reached (``present`` 0 everywhere) keeps no gradient, so Adam leaves it alone, as it
        does one process's parameter without ``.grad``."""
        both = self._sum_over_processes(torch.cat((gradient, present, gradient.new_tensor([float(pending)]))))
        n = int(both[-1])
        if n == 0:
            return
        offset, reached = 0, both[gradient.numel():-1]
        for j, q in enumerate(learned):
            q.grad = (both[offset : offset + q.numel()] / n).view_as(q).clone() if reached[j] > 0 else None
            offset += q.numel()
        rate = learning_rate(self.optimizer_steps, self.current_epoch, lr=self.lr, lr_final=self.lr_final,
                             warmup_steps=self.warmup_steps, epochs=self.trainer.max_epochs)
        for group in opt.optimizer.param_groups if hasattr(opt, "optimizer") else opt.param_groups:
            group["lr"] = rate * group.get("scale", 1.0)
        self.clip_gradients(opt, gradient_clip_val=self.gradient_clip, gradient_clip_algorithm="norm")
        opt.step()
        opt.zero_grad()
        self.optimizer_steps += 1
        self._add_to_average()
        self.trained_windows += n
        self.log("train/lr", rate, on_step=True, batch_size=1)
        for name, value in self.params.values().items():
            if self.params.raw[name].requires_grad:
                self.log(f"params/{name}", value, on_step=True, batch_size=1)

    def _averaged_epochs(self) -> tuple[int, int] | None:
        """The first and last epoch (from 1) whose steps ``model.average_epochs`` averages, or None."""
        last = self.trainer.max_epochs if self._trainer is not None else None
        if not self.average_epochs or not last or last < 1:
            return None
        return max(1, last - self.average_epochs + 1), last

    def _learned_tensors(self) -> dict[str, torch.Tensor]:
        """Every learned tensor by name: the parameters' optimiser coordinates and the adaptive
        networks' weights (``adaptive.KIND.NAME``)."""
        out = {n: q for n, q in self.params.raw.items() if q.requires_grad}
        out.update({f"adaptive.{n}": q for n, q in self.params.adaptive.named_parameters() if q.requires_grad})
        return out

    def _add_to_average(self) -> None:
        span = self._averaged_epochs()
        if span is None or self.current_epoch + 1 < span[0]:
            return
        for name, q in self._learned_tensors().items():
            value = q.detach().to(torch.float64)
            self._sums[name] = self._sums[name] + value if name in self._sums else value.clone()
        self._summed += 1

    def use_average(self) -> str | None:
        """Load the mean of the parameters after every optimiser step of the last
        ``model.average_epochs`` epochs (the optimiser's coordinates and the adaptive networks'
        weights) and return the label the next validation records them under (``mean 4-6``);
        None, loading nothing, where no step was averaged (Polyak-Ruppert averaging: the last
        iterate's scatter from step to step averaged out)."""
        span = self._averaged_epochs()
        if span is None or self._summed == 0:
            return None
        with torch.no_grad():
            for name, q in self._learned_tensors().items():
                q.copy_((self._sums[name] / self._summed).to(q.dtype))
        first, last = span
        self._next_label = f"mean {first}-{last}" if first < last else f"mean {last}"
        return self._next_label

    def gate_variants(self, chosen: Mapping) -> Iterator[str]:
        """Load, one after another, the parameters of the validation ``chosen`` (a
        :attr:`history` entry) with the flow gate's threshold at ``χ²₁(p)`` for each ``p`` of
        ``model.select_flow_gate``, and yield the label the next validation records each under
        (``epoch 3, gate 0.95``): each one more candidate for :meth:`select_best`, chosen's own
        learned gate competing as it is. The adaptive networks stay as :meth:`select_best` loaded
        them (``chosen``'s). A ``p`` whose threshold lies outside the gate's bound is said so and
        left out."""
        for p in self.select_flow_gate:
            threshold = chi2_quantile(p, 1)
            try:
                a = self.params.coordinate("flow_gate_threshold", threshold)
            except ValueError as error:
                log.info(f"model.select_flow_gate: gate {p:g} not tried: {error}")
                continue
            with torch.no_grad():
                for name, value in chosen["raw"].items():
                    self.params.raw[name].fill_(a if name == "flow_gate_threshold" else value)
            self._next_label = f"{chosen['label']}, gate {p:g}"
            yield self._next_label

    def _sum_over_processes(self, values: torch.Tensor, reduce: str = "sum") -> torch.Tensor:
        """``values`` summed (or their maximum) over the training processes (itself in one process)."""
        if not in_distributed_run():
            return values
        out = values.clone()
        op = torch.distributed.ReduceOp.MAX if reduce == "max" else torch.distributed.ReduceOp.SUM
        torch.distributed.all_reduce(out, op=op)
        return out

    def _log_windows(self, mean_loss: torch.Tensor, losses: list) -> None:
        """Log the window group's mean loss and, per method, its windows' figures (``losses``:
        ``[(method, WindowLoss, likelihood or None)]``)."""
        self.log("train/loss", mean_loss, on_step=True, prog_bar=True, batch_size=len(losses))
        for method in dict.fromkeys(m for m, _, _ in losses):
            mine = [w for m, w, _ in losses if m == method]
            likelihoods = [x.detach() for m, _, x in losses if m == method and x is not None]
            if likelihoods:
                self.log(f"train/{method}/innovation_nll", torch.stack(likelihoods).mean(), on_step=True,
                         batch_size=len(likelihoods))
            n = len(mine)
            self.log(f"train/{method}/rmse_m", torch.stack([w.rmse_m for w in mine]).mean(), on_step=True, batch_size=n)
            if self.nll_weight > 0:
                self.log(f"train/{method}/nll", torch.stack([w.nll for w in mine]).mean(), on_step=True, batch_size=n)
            if self.loss == "segments":
                self.log(f"train/{method}/segment_rmse_m", torch.stack([w.segment_rmse_m for w in mine]).mean(),
                         on_step=True, batch_size=n)
            if self.innovation_weight > 0 and not likelihoods:
                self.log(f"train/{method}/innovation_nll", torch.stack([w.innovation_nll for w in mine]).mean(),
                         on_step=True, batch_size=n)
            if self.orientation_weight > 0:
                self.log(f"train/{method}/orientation_rmse_rad",
                         torch.stack([w.orientation_rmse_rad for w in mine]).mean(), on_step=True, batch_size=n)

    def _skip(self, n: int) -> None:
        self.skipped_windows += n

    def filter_config(self, params: FilterParameters, *, training: bool) -> NavigationConfig:
        """The filter's configuration with ``params``' values: soft gates in a training step
        (the flow recheck off there without ``model.recheck_while_training``), hard otherwise."""
        return params.apply(self.base, training=training, device=self.device,
                            recheck=self.recheck_while_training or not training)

    # ------------------------------------------------------------------ held-out
    def _errors(self, seqs: Sequence[TrainingSequence], params: FilterParameters, *,
                smoother: bool) -> dict[str, list[tuple[float, float]]]:
        """``{method: [(filter, smoother) RMSE (m) of each sequence of seqs]}`` for every method
        with ``params`` (hard gates, no gradient) after the SE(3) alignment of Table I, as
        :func:`~flowins.training.unroll.sequences_errors` computes them (the smoother's NaN
        without ``smoother``); every sequence under every method runs in one batched filter
        pass (the dropout rate applies to the rows whose flow has dropout moments), split over
        ``filter.workers`` processes on the CPU (its tensors made without a graph, so that none
        crosses to a worker); with ``trainer=ddp`` each process runs its share (:meth:`_share`)
        and the values are summed over the processes (each entry comes from one of them)."""
        with torch.no_grad():
            config = self.filter_config(params, training=False)
        pairs = [(k, method) for method in self.methods for k in range(len(seqs))]
        moments = any(_has_moments(seqs[k], m) for k, m in pairs)
        p = float(params.value("dropout_p").detach()) if moments else None
        mine = self._share(seqs, pairs)
        values = sequences_errors([seqs[pairs[r][0]] for r in mine], [pairs[r][1] for r in mine], config,
                                  dropout_p=p, smoother=smoother) if mine else []
        if in_distributed_run():  # trainer=ddp: every process its share, everyone's values everywhere
            table = torch.zeros(len(pairs), 2, dtype=torch.float64, device=self.device)
            if mine:
                table[mine] = torch.tensor(values, dtype=torch.float64, device=self.device)
            values = [tuple(row) for row in self._sum_over_processes(table).tolist()]
        errors = {method: [(math.nan, math.nan)] * len(seqs) for method in self.methods}
        for (k, m), value in zip(pairs, values):
            errors[m][k] = value
        return errors

    def _share(self, seqs: Sequence[TrainingSequence], pairs: Sequence[tuple[int, str]]) -> list[int]:
        """The rows of ``pairs`` (sequence index, method) this process runs: all of them in one
        process; with several (``trainer=ddp``), a part of about equal work each
        (:func:`~flowins.parallel.split_by_load`, the same split in every process)."""
        if not in_distributed_run():
            return list(range(len(pairs)))
        world, rank = torch.distributed.get_world_size(), torch.distributed.get_rank()
        parts = split_by_load([run_load(sequence_load(seqs[k], m)) for k, m in pairs], world)
        return parts[rank] if rank < len(parts) else []

    def _filter_rmse(self, seqs: Sequence[TrainingSequence], params: FilterParameters) -> dict[str, list[float]]:
        """``{method: [filter RMSE (m) of each sequence]}`` (:meth:`_errors` without the smoother)."""
        return {m: [f for f, _ in v] for m, v in self._errors(seqs, params, smoother=False).items()}

    def _select_sequences(self) -> list[TrainingSequence]:
        return list(getattr(self.trainer.datamodule, "select_sequences", []))

    def _select_rmse(self, params: FilterParameters) -> dict[str, list[float]]:
        """``{method: [RMSE of each select sequence]}`` with ``params``; empty without select sequences."""
        seqs = self._select_sequences()
        return self._filter_rmse(seqs, params) if seqs else {}

    def validation_step(self, batch: TrainingSequence, batch_idx: int) -> None:
        for method, (rmse,) in self._filter_rmse([batch], self.params).items():
            self._val.setdefault(method, []).append(rmse)
            self.log(f"val/{method}/filter_rmse_m", rmse, on_epoch=True, batch_size=1, sync_dist=True)

    def on_validation_epoch_end(self) -> None:
        """Record this validation (``start`` when run before the first step, by ``trainer.validate``;
        ``epoch N`` after training epoch ``N``) with the parameters it scored."""
        per_method, self._val = self._val, {}
        if self.trainer.sanity_checking or not per_method:
            return
        means = {m: sum(v) / len(v) for m, v in per_method.items()}
        score = _mean_score(per_method)
        self.log("val/rmse_mean_m", score, prog_bar=True, batch_size=1, sync_dist=True)
        fitting = self.trainer.state.fn == TrainerFn.FITTING
        label = f"epoch {self.current_epoch + 1}" if fitting else self._next_label or "start"
        self._next_label = None
        entry = {
            "label": label,
            "step": self.optimizer_steps, "rmse_m": means, "score": score,
            "raw": {n: float(q.detach()) for n, q in self.params.raw.items()},
            "values": self.params.values(),
        }
        select = self._select_rmse(self.params)
        if select:
            for method, values in select.items():
                self.log(f"select/{method}/filter_rmse_m", sum(values) / len(values), batch_size=1, sync_dist=True)
            entry["select_rmse_m"] = select
            entry["select_score"] = _mean_score(select)
            self.log("select/rmse_mean_m", entry["select_score"], batch_size=1, sync_dist=True)
        self.history.append(entry)
        if len(self.params.adaptive):
            self._adaptive_states[entry["label"]] = self.params.adaptive_state()
        now = time.monotonic()
        self._first_validation = self._first_validation or now
        if self.trainer.is_global_zero:  # one line per validation, also where no progress bar is shown
            rows = ", ".join(f"{m} {v:.3f}" for m, v in means.items())
            of = f" of {self.trainer.max_epochs}" if fitting else ""
            long = f"; long held-out walks {entry['select_score']:.3f} m" if select else ""
            log.info(f"{entry['label']}{of}: held out {score:.3f} m ({rows}){long}; {self.optimizer_steps} steps, "
                     f"{now - self._first_validation:.0f} s after the first validation")

    def select_best(self) -> dict:
        """Load the parameters of the best validation so far and return it: the lowest mean RMSE
        over the ``select`` sequences and methods where the validations ran them
        (``select_score``), the lowest mean held-out (``val``) RMSE otherwise (``score``); the
        earliest on a tie, so the start wins over an epoch that is no better."""
        if not self.history:
            raise ValueError("select_best: no validation has run (trainer.validate before fit scores the start)")
        best = min(self.history, key=_selection_score)
        with torch.no_grad():
            for name, value in best["raw"].items():
                self.params.raw[name].fill_(value)
        for kind, weights in self._adaptive_states.get(best["label"], {}).items():
            self.params.adaptive[kind].load_state_dict(weights)
        return best

    def _candidates(self) -> dict[str, FilterParameters]:
        """The parameter sets the held-out test compares: the learned ones and the references."""
        candidates = {"learned": self.params}
        for name, values in self.reference.items():
            candidates[name] = FilterParameters(values, learn=())
        return candidates

    def test_step(self, batch: TrainingSequence, batch_idx: int) -> None:
        for label, params in self._candidates().items():
            for method, (rmse,) in self._filter_rmse([batch], params).items():
                self._heldout.setdefault(label, {}).setdefault(method, []).append(rmse)
                self.log(f"test/{label}/{method}/filter_rmse_m", rmse, on_epoch=True, batch_size=1, sync_dist=True)

    def on_test_epoch_end(self) -> None:
        seqs = self._select_sequences()
        if seqs:  # the long held-out walks, filter and smoother
            for label, params in self._candidates().items():
                for method, errors in self._errors(seqs, params, smoother=True).items():
                    filtered, smoothed = [e[0] for e in errors], [e[1] for e in errors]
                    self._heldout_select.setdefault(label, {})[method] = filtered
                    self._heldout_select_smoother.setdefault(label, {})[method] = smoothed
                    for kind, values in (("filter", filtered), ("smoother", smoothed)):
                        self.log(f"test/{label}/select/{method}/{kind}_rmse_m", sum(values) / len(values),
                                 batch_size=1, sync_dist=True)
        table = heldout_table(self._heldout, self.methods, self._heldout_select, self._heldout_select_smoother)
        log.info("\nheld-out filter RMSE (m, Table I alignment), mean over the held-out sequences"
                 + ("; select: filter / smoother, mean ± std over the data.select sequences"
                    if self._heldout_select else "") + "\n")
        log.info(table)
        if self.output_dir and self.trainer.is_global_zero:
            out = Path(self.output_dir)
            out.mkdir(parents=True, exist_ok=True)
            report = {"rmse_m": self._heldout, "learned_values": self.params.values(), "reference": self.reference}
            if self._heldout_select:
                report["select_rmse_m"] = self._heldout_select
                report["select_smoother_rmse_m"] = self._heldout_select_smoother
            (out / "heldout.json").write_text(json.dumps(report, indent=2))
            (out / "heldout.txt").write_text(table + "\n")


def _has_moments(seq: TrainingSequence, method: str) -> bool:
    return has_moments(seq.sources(method)[1])


def _mean_score(per_method: Mapping[str, Sequence[float]]) -> float:
    """The mean over methods of each method's mean; ``inf`` when not finite (a diverged
    filter is never the best)."""
    score = sum(sum(v) / len(v) for v in per_method.values()) / len(per_method)
    return score if math.isfinite(score) else math.inf


def _selection_score(entry: Mapping) -> float:
    """What :meth:`FilterLearner.select_best` minimises: the ``select`` score where there is one."""
    return entry.get("select_score", entry["score"])


def _mean_std(values: Sequence[float]) -> str:
    """``mean ± std`` (the population standard deviation) of ``values``, 2 decimals, in m
    (``nan`` where a value is not finite)."""
    mean = sum(values) / len(values)
    std = math.sqrt(sum((v - mean) ** 2 for v in values) / len(values)) if math.isfinite(mean) else math.nan
    return f"{mean:.2f} ± {std:.2f} m"


def heldout_table(results: Mapping[str, Mapping[str, list[float]]], methods: Sequence[str],
                  select: Mapping[str, Mapping[str, list[float]]] | None = None,
                  select_smoother: Mapping[str, Mapping[str, list[float]]] | None = None) -> str:
    """Fixed-width table: one row per parameter set, one column per method (mean RMSE over
    the held-out sequences) and, with ``select`` (``{label: {method: [RMSE]}}``), one more
    column per method: mean ± std over the ``select`` sequences, followed by the smoother's
    where ``select_smoother`` (the same shape) has them."""
    select, smoother = select or {}, select_smoother or {}
    extra = [m for m in methods if any(m in per_method for per_method in select.values())]
    both = bool(smoother)
    width = 40 if both else 26
    lines = [f"{'parameters':<14}" + "".join(f"{m:>18}" for m in methods)
             + "".join(f"{'select ' + m + (' filter / smoother' if both else ''):>{width}}" for m in extra)]
    for label in list(dict.fromkeys([*results, *select])):
        per_method, long, long_s = results.get(label, {}), select.get(label, {}), smoother.get(label, {})
        cells = []
        for m in methods:
            v = per_method.get(m, [])
            cells.append(f"{sum(v) / len(v):>16.2f} m" if v else f"{'n/a':>18}")
        for m in extra:
            cell = _mean_std(long[m]) if long.get(m) else "n/a"
            if both:
                cell = cell.removesuffix(" m") + " / " + (_mean_std(long_s[m]) if long_s.get(m) else "n/a")
            cells.append(f"{cell:>{width}}")
        lines.append(f"{label:<14}" + "".join(cells))

    def reduction(columns: Mapping[str, Mapping[str, list[float]]], m: str) -> str:
        a, b = columns.get("start", {}).get(m), columns.get("learned", {}).get(m)
        return f"{100 * (1 - (sum(b) / len(b)) / (sum(a) / len(a))):.1f} %" if a and b else ""

    change = [f"{reduction(results, m):>18}" for m in methods]
    for m in extra:
        cell = reduction(select, m)
        if both and cell:
            cell = cell.removesuffix(" %") + " / " + (reduction(smoother, m) or "n/a")
        change.append(f"{cell:>{width}}")
    if ("start" in results and "learned" in results) or ("start" in select and "learned" in select):
        lines.append(f"{'reduction':<14}" + "".join(change))
    return "\n".join(lines)


def selection_table(history: list[dict], chosen: dict) -> str:
    """The held-out RMSE of every validation (the start, then each epoch), the chosen one
    marked; with ``data.select``, each method's mean ± std over the select sequences and
    their mean (the score the choice minimises) beside the ``val`` columns."""
    methods = list(history[0]["rmse_m"])
    select = [m for m in history[0].get("select_rmse_m", {})]
    title = ("held-out filter RMSE (m) at each validation; the checkpoint is the lowest select mean"
             if select else "held-out filter RMSE (m) at each validation; the checkpoint is the best of them")
    width = max(10, *(len(entry["label"]) + 1 for entry in history))
    lines = [title, f"{'':<{width}}" + "".join(f"{m:>18}" for m in methods) + f"{'mean':>10}"
             + "".join(f"{'select ' + m:>26}" for m in select) + (f"{'select mean':>14}" if select else "")]
    for entry in history:
        mark = "  <- chosen" if entry is chosen else ""
        long = "".join(f"{_mean_std(entry['select_rmse_m'][m]):>26}" for m in select)
        if select:
            long += f"{entry['select_score']:>14.3f}"
        lines.append(f"{entry['label']:<{width}}" + "".join(f"{entry['rmse_m'][m]:>18.3f}" for m in methods)
                     + f"{entry['score']:>10.3f}" + long + mark)
    return "\n".join(lines)
