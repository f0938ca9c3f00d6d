"""Monte Carlo dropout (Gal & Ghahramani 2016) with the deterministic part run once.

In the paper, dropout acts at one layer of the flow network at test time and the
flow's per-pixel standard deviation over ``N_MC`` passes is its uncertainty.
Everything upstream of that layer does not depend on the dropout mask, so
:func:`mc_samples` takes the upstream features computed **once**, repeats them
``N`` times along the batch, applies the dropout and runs only the downstream
``head`` (in chunks of passes, to bound memory).

What is left per pass is memory traffic over full-resolution features, so on a
CPU the mask is made of random bytes laid out in the features' own memory order
(:func:`keep_like`), the dropped features of every pass share one buffer, and a
network may apply the mask itself strip by strip (``masked_head``).

:class:`MCDropout` is ordinary dropout that stays active in eval mode (``p = 0``
disables it); :class:`ConcreteDropout` is the relaxed Bernoulli ("concrete")
dropout of Gal, Hron & Kendall (2017) whose rate is a differentiable parameter
(stored as a logit), for learning the rate end to end.
"""
from __future__ import annotations

import math
from collections.abc import Callable, Sequence

import torch
from torch import Tensor, nn

from flowins.flow.base import mc_statistics


def keep_probability(p: float, device: torch.device | str = "cpu") -> float:
    """The exact keep probability of :func:`keep_mask` for rate ``p`` on ``device``."""
    return 1.0 - p if torch.device(device).type != "cpu" else 1.0 - int(round(256 * p)) / 256.0


def _cpu_bytes(n: int, generator: torch.Generator | None) -> Tensor:
    """``(⌈n/7⌉, 7)`` uniform random bytes (uint8 view, not contiguous): each 64-bit draw,
    uniform on ``[0, 2⁶³)``, gives seven full bytes (its top byte has only 7 random bits)."""
    draws = torch.empty((n + 6) // 7, dtype=torch.int64).random_(generator=generator)
    return draws.view(torch.uint8).view(-1, 8)[:, :7]


def drop_mask(
    shape: Sequence[int], p: float, *, device: torch.device | str = "cpu", generator: torch.Generator | None = None
) -> Tensor:
    """The complement of :func:`keep_mask`: ``True`` where an element is dropped
    (drawn from ``generator``, on ``device``, or from torch's global generator)."""
    device = torch.device(device)
    if device.type != "cpu":
        return torch.rand(tuple(shape), device=device, generator=generator) < p
    n = math.prod(int(d) for d in shape)
    return (_cpu_bytes(n, generator) < int(round(256 * p))).reshape(-1)[:n].view(tuple(shape))


def _dense(x: Tensor) -> bool:
    """Whether ``x``'s elements fill its memory without gaps or overlaps (any dim order)."""
    order = sorted(range(x.ndim), key=lambda d: x.stride(d), reverse=True)
    return x.permute(order).is_contiguous()


def keep_like(x: Tensor, p: float, *, generator: torch.Generator | None = None) -> Tensor:
    """A bool keep-mask with the shape *and the strides* of ``x``, drop rate ``≈ p``.

    On the CPU, element ``k`` of ``x``'s *memory* takes byte ``k`` of the stream of
    :func:`drop_mask`, so a contiguous ``x`` gets exactly ``~drop_mask(x.shape, p)``,
    and a channels-last ``x`` a mask in its own memory order: ``x * keep_like(x, p)``
    then reads both in one sweep (a mask in another order costs several times more).
    An ``x`` that is not dense (a strided view) gets the contiguous mask.
    """
    if x.device.type != "cpu" or not _dense(x):
        return ~drop_mask(x.shape, p, device=x.device, generator=generator)
    n = x.numel()
    flat = (_cpu_bytes(n, generator) >= int(round(256 * p))).reshape(-1)[:n]
    return flat.as_strided(x.shape, x.stride())


def keep_mask(shape: Sequence[int], p: float, *, device: torch.device | str = "cpu") -> tuple[Tensor, float]:
    """A Bernoulli keep-mask (bool, ``shape``) with drop rate ``≈ p``, and its exact keep probability.

    On the CPU, drawing one random number per element dominates Monte Carlo
    dropout at full resolution, so the mask is made from random *bytes*: each
    64-bit draw (uniform on ``[0, 2⁶³)``) gives seven uniform bytes, and an element
    is dropped when its byte is below ``round(256 p)``. The drop rate is therefore
    ``p`` rounded to a multiple of 1/256 (0.2 -> 0.1992), which the returned keep
    probability states exactly, so the rescaling stays unbiased. Elsewhere (CUDA)
    the mask is ``rand < 1 - p``.
    """
    return ~drop_mask(shape, p, device=device), keep_probability(p, device)


class MCDropout(nn.Module):
    """Element-wise dropout with rate ``p``, active in train *and* eval mode.

    Kept elements are scaled by ``1 / keep``; the mask comes from :func:`keep_like`
    (on the CPU the rate is ``p`` rounded to a multiple of 1/256), in the memory order
    of the input: a channels-last input keeps its layout.
    """

    def __init__(self, p: float = 0.2, *, seed: int | None = None):
        super().__init__()
        if not 0.0 <= p < 1.0:
            raise ValueError(f"MCDropout: p={p}; expected 0 <= p < 1")
        self.p = float(p)
        self.seed = seed
        self._generators: dict[str, torch.Generator] = {}

    def forward(self, x: Tensor) -> Tensor:
        if self.p == 0:
            return x
        return self.drop_prescaled(x * (1.0 / keep_probability(self.p, x.device)))

    def drop_prescaled(self, x_scaled: Tensor, *, out: Tensor | None = None) -> Tensor:
        """Dropout of features already divided by the keep probability (one mask, one product):
        Monte Carlo passes over the same features scale them once, not once per pass.
        ``out``: a tensor like ``x_scaled`` to write into (a buffer reused across passes
        without autograd: a fresh tensor of tens of MB costs its page faults every pass)."""
        if self.p == 0:
            return x_scaled
        keep = self.keep(x_scaled)
        return torch.mul(x_scaled, keep, out=out) if out is not None else x_scaled * keep

    def keep(self, x: Tensor) -> Tensor:
        """One pass's bool keep-mask for ``x`` (:func:`keep_like`, from this layer's generator)."""
        return keep_like(x, self.p, generator=self.generator(x.device))

    def generator(self, device: torch.device | str) -> torch.Generator | None:
        """This layer's own generator on ``device``, seeded with ``seed`` (None: torch's global one)."""
        return _seeded_generator(self._generators, self.seed, device)

    def extra_repr(self) -> str:
        return f"p={self.p}" + ("" if self.seed is None else f", seed={self.seed}")


def _seeded_generator(generators: dict[str, torch.Generator], seed: int | None, device) -> torch.Generator | None:
    """A generator per device, created on first use and seeded with ``seed``: the masks of a
    run are reproducible (the same frame pairs in the same batches give the same flow σ)."""
    if seed is None:
        return None
    key = str(torch.device(device))
    if key not in generators:
        generators[key] = torch.Generator(device=device).manual_seed(int(seed))
    return generators[key]


class ConcreteDropout(nn.Module):
    """Relaxed Bernoulli dropout with a learnable rate ``p = sigmoid(p_logit)``.

    ``z = sigmoid((log p - log(1-p) + log u - log(1-u)) / temperature)``, ``u ~ U(0, 1)``,
    and ``x ↦ x (1 - z) / (1 - p)``; differentiable in ``p`` (and in ``x``).
    """

    def __init__(self, p: float = 0.2, temperature: float = 0.1, *, eps: float = 1e-7, seed: int | None = None):
        super().__init__()
        self.seed = seed
        self._generators: dict[str, torch.Generator] = {}
        if not 0.0 < p < 1.0:
            raise ValueError(f"ConcreteDropout: p={p}; expected 0 < p < 1")
        if temperature <= 0:
            raise ValueError(f"ConcreteDropout: temperature={temperature}; expected > 0")
        self.p_logit = nn.Parameter(torch.tensor(math.log(p) - math.log1p(-p)))
        self.temperature = float(temperature)
        self.eps = float(eps)

    @property
    def p(self) -> Tensor:
        return torch.sigmoid(self.p_logit)

    def forward(self, x: Tensor) -> Tensor:
        p = self.p.to(x.dtype)
        u = torch.rand(x.shape, dtype=x.dtype, device=x.device,
                       generator=_seeded_generator(self._generators, self.seed, x.device)).clamp(self.eps, 1.0 - self.eps)
        logit = (torch.log(p) - torch.log1p(-p) + torch.log(u) - torch.log1p(-u)) / self.temperature
        keep = 1.0 - torch.sigmoid(logit)
        return x * keep / (1.0 - p)


def mc_samples(
    head: Callable[..., Tensor],
    features: Tensor,
    dropout: nn.Module,
    passes: int,
    *,
    context: Sequence[Tensor] = (),
    chunk: int | None = None,
    masked_head: Callable[..., Tensor] | None = None,
) -> Tensor:
    """``(N, B, ...)`` outputs of ``head(dropout(features), *context)`` over ``N`` passes.

    ``features`` ``(B, ...)`` and ``context`` (tensors that bypass the dropout, each
    ``(B, ...)``) are computed once by the caller; they are repeated along the
    batch, ``chunk`` passes at a time (default: all at once). ``head`` must return
    new tensors, not views of its input: without autograd the dropped features of
    every pass are written into one buffer.

    ``masked_head(scaled, keep, *context)``, optional, computes ``head(scaled * keep,
    *context)`` itself (e.g. strip by strip, applying the mask as it goes); it serves
    :class:`MCDropout` passes run one at a time (``chunk=1``) and draws the same masks.
    """
    if passes < 1:
        raise ValueError(f"mc_samples: passes={passes}; expected >= 1")
    B = features.shape[0]
    chunk = passes if chunk is None else max(1, int(chunk))
    prescaled = isinstance(dropout, MCDropout) and dropout.p > 0
    if prescaled:  # scale once for all passes
        features = features * (1.0 / keep_probability(dropout.p, features.device))
    outputs, buffer = [], None
    for start in range(0, passes, chunk):
        n = min(chunk, passes - start)
        # one pass at a time needs no copy of the (large) upstream features
        x = features if n == 1 else features.repeat(n, *([1] * (features.ndim - 1)))
        ctx = [c if n == 1 else c.repeat(n, *([1] * (c.ndim - 1))) for c in context]
        if prescaled and masked_head is not None and n == 1:
            out = masked_head(x, dropout.keep(x), *ctx)
            outputs.append(out.reshape(n, B, *out.shape[1:]))
            continue
        if prescaled and not torch.is_grad_enabled():
            # nothing keeps a pass's dropped features (``head`` returns new tensors): one buffer serves every pass
            if buffer is None or buffer.shape != x.shape:
                buffer = torch.empty_like(x)
            dropped = dropout.drop_prescaled(x, out=buffer)
        elif prescaled:
            dropped = dropout.drop_prescaled(x)
        else:
            dropped = dropout(x)
        out = head(dropped, *ctx)
        outputs.append(out.reshape(n, B, *out.shape[1:]))
    return torch.cat(outputs, dim=0)


def mc_flow(
    head: Callable[..., Tensor],
    features: Tensor,
    dropout: nn.Module,
    passes: int,
    *,
    context: Sequence[Tensor] = (),
    chunk: int | None = None,
    floor: float = 0.0,
) -> tuple[Tensor, Tensor, Tensor]:
    """``(mean, std, samples)`` of :func:`mc_samples` (std over passes, unbiased)."""
    samples = mc_samples(head, features, dropout, passes, context=context, chunk=chunk)
    mean, std = mc_statistics(samples, floor=floor)
    return mean, std, samples
