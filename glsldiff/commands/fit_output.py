"""What ``glsldiff fit`` prints: one progress line per N evaluations (no redrawn bars, so a
log stays readable) and a one-line verdict on the result."""
from __future__ import annotations

import math
from typing import Callable

from glsldiff.inverse.fit import STOP_FRACTION, FitResult
from glsldiff.inverse.optimize import Record

#: The paper's figure-11 level of a good fit (E of the diffuse BSSRDF against the truth).
GOOD_E = 0.01
#: Median relative error per node of sigma_a and sigma_s' that counts as recovered.
GOOD_COEFFICIENT = 0.15


class FitProgress:
    """``callback(channel, record)`` of :func:`glsldiff.inverse.fit.fit_measurements`: prints
    the first evaluation of each channel, every ``every``-th, one at least every
    ``interval_s`` seconds of the channel's fit (a 1.3 M-node evaluation takes 35 s: every 40th
    alone would be 23 minutes apart), and the channel's last."""

    def __init__(self, max_evals: int, every: int | None = None, out: Callable[[str], None] = print,
                 interval_s: float = 300.0) -> None:
        self.max_evals = max_evals
        self.every = every or max(1, math.ceil(max_evals / 5))
        self.interval_s = interval_s
        self.out = out
        self._channel = -1
        self._pending: Record | None = None   # the channel's latest record, not yet printed
        self._printed_at = 0.0                # the channel's seconds at the last printed record

    def __call__(self, channel: int, rec: Record) -> None:
        if channel != self._channel:
            self.flush()
            self._channel, self._printed_at = channel, 0.0
        self._pending = rec
        if rec.evaluation == 1 or rec.evaluation % self.every == 0 or rec.seconds - self._printed_at >= self.interval_s:
            self.flush()

    def flush(self) -> None:
        """Print the latest record if it was not printed yet (a channel's last evaluation)."""
        rec, self._pending = self._pending, None
        if rec is None:
            return
        self._printed_at = rec.seconds
        grad = "" if math.isnan(rec.grad_norm) else f"  |grad| {rec.grad_norm:.2e}"
        self.out(f"fit {'RGB'[self._channel]}: evaluation {rec.evaluation:>{len(str(self.max_evals))}}/"
                 f"{self.max_evals}  {rec.seconds:7.1f} s  f {rec.value:.3e}  data {rec.data:.3e}{grad}")


def verdict(result: FitResult, E: float | None = None, coefficients: list[dict[str, float]] | None = None
            ) -> str:
    """One line: converged or not, E against the paper's level, the coefficients against the
    truth, and what the measurements do not determine."""
    fits = result.channels[:1] if result.shared else result.channels
    names = "RGB" if not result.shared else "grey"
    stalled = [names[c] if not result.shared else names for c, f in enumerate(fits) if not f.converged]
    if result.interrupted:
        parts = ["interrupted: the best material so far is saved (resume with --resume)"]
    elif stalled:
        statuses = {f.trace.status for f in fits if not f.converged}
        o = result.options
        timed = math.isfinite(o.max_seconds)
        if statuses == {"budget spent"}:
            budget = f"{o.max_evals} evaluations or {o.max_seconds:g} s" if timed else f"{o.max_evals} evaluations"
            raise_ = "--max-evals or --max-seconds" if timed else "--max-evals"
            why = (f"objective, data term plus regularisation, >= {STOP_FRACTION:g} of the measured power when the "
                   f"budget was spent: {budget} per channel): raise {raise_}")
        else:
            why = "; ".join(sorted(statuses)) + ")"
        parts = [f"NOT converged in {', '.join(stalled)} ({why}"]
    elif all(f.trace.status == "converged (f < eps)" for f in fits):
        parts = [f"converged (objective, data term plus regularisation, < {STOP_FRACTION:g} of the measured power)"]
    else:   # another stop rule: say which, the objective did not reach the paper's level
        parts = ["converged (" + "; ".join(f"{names if result.shared else names[c]}: "
                                          f"{f.trace.status.removeprefix('converged ').strip('()') or 'converged'}"
                                          for c, f in enumerate(fits)) + ")"]
    if E is not None:
        parts.append(f"E = {E:.4f} {'<=' if E <= GOOD_E else '>'} {GOOD_E:g} (the paper's figure-11 level)")
    if coefficients:
        worst = max(max(r["sigma_a_median_rel_err"], r["sigma_s_median_rel_err"]) for r in coefficients)
        parts.append(f"coefficients {'recovered' if worst <= GOOD_COEFFICIENT else 'NOT recovered'}: worst median "
                     f"error per node {100 * worst:.0f} % (target {100 * GOOD_COEFFICIENT:.0f} %)")
        if max(r["sigma_a_median_rel_err"] for r in coefficients) > GOOD_COEFFICIENT:
            parts.append("steady-state captures do not fix sigma_a per node, only with sigma_s' "
                         "(docs/guide/inverse.md, 'What the captures determine')")
    loose = []
    for c, f in enumerate(fits):
        if f.ranges is not None:
            loose += [f"{name} ({names if result.shared else names[c]})" for name, ok
                      in zip(("sigma_a", "sigma_s'"), f.ranges.determined) if not ok]
    if loose:
        parts.append(f"the measurements do not determine {', '.join(loose)}")
    return "verdict: " + "; ".join(parts)
