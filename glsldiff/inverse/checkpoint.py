"""Checkpoints of a long fit: where each channel stands, saved every few minutes and on Ctrl-C,
so that ``glsldiff fit --resume`` continues instead of starting again.

A checkpoint is an ``.npz`` beside the output (``OUT_checkpoint.npz``) holding, per channel,
the homogeneous result and its ranges, the records of both stages, and the best material of
the heterogeneous stage so far (active-node vectors). A resumed channel skips its homogeneous
fit and restarts the heterogeneous minimiser from that best material with the evaluations
left of the same budget (the minimiser's own memory, e.g. L-BFGS's curvature pairs, is not
kept: the path after the restart differs from an uninterrupted run's). Finished channels are
taken as they are. The checkpoint names the measurements and the options that shape the
objective (a digest): resuming with others is an error, not a silent mix.
"""
from __future__ import annotations

import hashlib
import math
import os
import time
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from glsldiff.core.errors import InputError
from glsldiff.core.io import read_npz, write_npz
from glsldiff.inverse.measurements import Measurements
from glsldiff.inverse.optimize import Record, Trace
from glsldiff.inverse.ranges import CoefficientRanges

__all__ = ["ChannelProgress", "Checkpoint", "load_checkpoint", "checkpoint_path", "CHECKPOINT_EVERY_S"]

#: Default seconds between checkpoints.
CHECKPOINT_EVERY_S = 120.0
#: FitOptions fields that change the objective or its start: a resume must use the same.
_KEYED_OPTIONS = ("method", "lam", "lam_mu", "depth_weight", "stencil", "face_mean", "kappa0", "mu0", "homogeneous_evals",
                  "parameterization", "mu_gain", "exitant")


class ChannelProgress:
    """Where one channel's fit stands (what a checkpoint keeps)."""

    def __init__(self, channel: int, homogeneous: tuple[float, float], homogeneous_trace: Trace,
                 ranges: CoefficientRanges | None, trace: Trace, kappa: NDArray | None, mu: NDArray | None,
                 done: bool) -> None:
        self.channel, self.homogeneous, self.homogeneous_trace = channel, homogeneous, homogeneous_trace
        self.ranges, self.trace, self.kappa, self.mu, self.done = ranges, trace, kappa, mu, done


def checkpoint_path(out: str | os.PathLike) -> Path:
    """``OUT_checkpoint.npz`` beside the fit's output ``OUT``."""
    out = Path(out)
    return out.with_name(out.stem + "_checkpoint.npz")


def digest(meas: Measurements, options: object) -> str:
    """What a checkpoint belongs to: the measurements' arrays and the keyed options."""
    h = hashlib.sha256()
    for a in (np.asarray(meas.shape), np.float64(meas.h), np.float64(meas.eta), meas.incoming, meas.radiance,
              meas.mask, meas.reflected, meas.reflected_mask):
        if a is not None:
            h.update(np.ascontiguousarray(a).tobytes())
    h.update(f"{meas.lit_face}{meas.observed_face}{meas.C}".encode())
    h.update(repr([getattr(options, k) for k in _KEYED_OPTIONS]).encode())
    return h.hexdigest()[:16]


def _records(trace: Trace) -> NDArray[np.float64]:
    return np.array([[r.evaluation, r.seconds, r.value, r.data, r.grad_norm] for r in trace.records],
                    dtype=np.float64).reshape(-1, 5)


def _trace(method: str, rows: NDArray, status: str) -> Trace:
    t = Trace(method, [Record(int(e), float(s), float(v), float(d), float(g)) for e, s, v, d, g in rows])
    t.status, t.converged = status, status.startswith("converged")
    t.seconds = float(rows[-1, 1]) if len(rows) else 0.0
    return t


class Checkpoint:
    """Writes the fit's :class:`ChannelProgress` to ``path`` (atomically) when :meth:`due`
    (every ``every_s`` seconds) and whenever asked with ``force``."""

    def __init__(self, path: str | os.PathLike, meas: Measurements, options: object,
                 every_s: float = CHECKPOINT_EVERY_S, method: str = "lbfgs") -> None:
        self.path = Path(path)
        self.key = digest(meas, options)
        self.every_s = every_s
        self.method = method
        self.channels: dict[int, ChannelProgress] = {}
        self._last = time.perf_counter()
        self.writes = 0

    def due(self) -> bool:
        return time.perf_counter() - self._last >= self.every_s

    def save(self, progress: ChannelProgress) -> None:
        """Record ``progress`` and write every channel's to the file."""
        self.channels[progress.channel] = progress
        arrays: dict[str, object] = {"key": self.key, "channels": np.array(sorted(self.channels))}
        for c, p in self.channels.items():
            r = p.ranges
            arrays.update({
                f"c{c}_done": p.done, f"c{c}_status": p.trace.status,
                f"c{c}_homogeneous": np.array(p.homogeneous, dtype=np.float64),
                f"c{c}_homogeneous_records": _records(p.homogeneous_trace),
                f"c{c}_homogeneous_status": p.homogeneous_trace.status,
                f"c{c}_records": _records(p.trace),
                f"c{c}_ranges": (np.array([r.sigma_a, *r.sigma_a_range, r.sigma_s, *r.sigma_s_range, r.tolerance,
                                           r.data]) if r is not None else np.full(8, np.nan)),
            })
            if p.kappa is not None:
                arrays[f"c{c}_kappa"], arrays[f"c{c}_mu"] = p.kappa, p.mu
        write_npz(self.path, **arrays)
        self._last = time.perf_counter()
        self.writes += 1

    def remove(self) -> None:
        """Delete the file (the fit finished and its output is written)."""
        self.path.unlink(missing_ok=True)


def load_checkpoint(path: str | os.PathLike, meas: Measurements, options: object,
                    method: str = "lbfgs") -> dict[int, ChannelProgress]:
    """The channels' progress saved in ``path``, checked against ``meas`` and ``options``."""
    d = read_npz(path, "checkpoint", ("key", "channels"))
    if str(d["key"]) != digest(meas, options):
        raise InputError(f"checkpoint {str(path)!r} belongs to other measurements or fit options ("
                         f"{', '.join(_KEYED_OPTIONS)} must match); delete it to start again or resume with the "
                         "original ones")
    out: dict[int, ChannelProgress] = {}
    try:
        for c in (int(x) for x in np.asarray(d["channels"]).reshape(-1)):
            rg = np.asarray(d[f"c{c}_ranges"], dtype=np.float64)
            ranges = None if math.isnan(rg[7]) else CoefficientRanges(
                float(rg[0]), (float(rg[1]), float(rg[2])), float(rg[3]), (float(rg[4]), float(rg[5])), float(rg[6]),
                float(rg[7]))
            k_h, m_h = (float(x) for x in d[f"c{c}_homogeneous"])
            out[c] = ChannelProgress(
                c, (k_h, m_h),
                _trace("homogeneous-trf", d[f"c{c}_homogeneous_records"], str(d[f"c{c}_homogeneous_status"])),
                ranges, _trace(method, d[f"c{c}_records"], str(d[f"c{c}_status"])),
                d.get(f"c{c}_kappa"), d.get(f"c{c}_mu"), bool(d[f"c{c}_done"]))
    except (KeyError, ValueError, IndexError) as exc:
        raise InputError(f"checkpoint {str(path)!r} is incomplete ({exc}); delete it to start again") from None
    return out
