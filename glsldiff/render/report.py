"""What one :meth:`glsldiff.render.renderer.Renderer.render` call did: which stages ran and
why, times in seconds (t1/t2/t3: passes 1-3), the solver's report, and notes."""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any


@dataclass
class RenderReport:
    """What one :meth:`Renderer.render` call did, with times in seconds."""

    passes: list[dict[str, Any]] = field(default_factory=list)
    seconds: dict[str, float] = field(default_factory=dict)
    renderer: str = ""
    solver: Any = None
    nodes: int = 0
    boundary_nodes: int = 0
    clamped_vertices: int = 0
    clamped_depth: float = 0.0      # the most negative exitance before clamping / the largest exitance
    clamped_deep: int = 0           # vertices clamped from below -1 % of the largest exitance
    image_size: tuple[int, int] = (0, 0)
    model: str = ""                 # the model that rendered the frame (split / diffusion, and how)
    notes: list[str] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)   # outside what was validated: one line each (stderr)

    def ran(self, name: str) -> bool:
        return any(p["pass"] == name and p["ran"] for p in self.passes)

    @property
    def frame_seconds(self) -> float:
        """t1 + t2 + t3 (what ran this frame)."""
        return sum(self.seconds.get(k, 0.0) for k in ("t1", "t2", "t3"))

    def lines(self) -> list[str]:
        out = [f"GL renderer: {self.renderer}",
               f"polygrid: {self.nodes} active nodes, {self.boundary_nodes} boundary; image {self.image_size[0]}x"
               f"{self.image_size[1]}"]
        for p in self.passes:
            state = f"ran     {p['seconds'] * 1e3:9.1f} ms" if p["ran"] else "skipped             "
            out.append(f"  {p['pass']:<8} {state}  {p['why']}")
        t = self.seconds
        fs = self.frame_seconds
        out.append(f"t1/t2/t3 = {t.get('t1', 0) * 1e3:.1f}/{t.get('t2', 0) * 1e3:.1f}/{t.get('t3', 0) * 1e3:.1f} ms, "
                   f"frame {fs * 1e3:.1f} ms = {1.0 / fs if fs > 0 else math.inf:.2f} fps-equivalent"
                   + (f" (setup {t['setup']:.2f} s)" if "setup" in t else ""))
        if self.solver is not None:
            out.append("solver: " + self.solver.summary())
        out.extend(self._clamped_lines())
        out.extend(self.notes)
        return out

    def _clamped_lines(self) -> list[str]:
        """The line on vertices whose exitant radiance (the split: the diffusion's fluence) was
        clamped to 0, if any."""
        if not self.clamped_vertices:
            return []
        what = "fluence" if self.model.startswith("split") else "exitant radiance"
        return [f"{what} clamped to 0 at {self.clamped_vertices} vertices: {self.clamped_deep} "
                f"from below -1 % of the largest (down to -{self.clamped_depth:.2g}: diffusion undershoot), "
                f"{self.clamped_vertices - self.clamped_deep} within 1 % (undershoot or the solve's tolerance; a "
                "tighter [options].tol tells them apart)"]

    def summary_lines(self) -> list[str]:
        """The short report of ``glsldiff render`` (:meth:`lines` is the full one): the grid, the
        model and material, the solver, the times, and clamped vertices if any."""
        t = self.seconds
        ran = [p for p in self.passes if p["ran"] and p["pass"] in ("pass1", "pass2", "pass3")]
        times = " + ".join(f"{p['pass'].replace('pass', 'pass ')} {p['seconds']:.2f}" for p in ran)
        why = [p["why"].removeprefix("first frame: ") for p in ran
               if p["pass"] == "pass2" and p["why"].startswith("first frame: ")]
        out = [f"grid: {self.nodes:,} nodes ({self.boundary_nodes:,} on the boundary); image {self.image_size[0]} x "
               f"{self.image_size[1]}; GL {self.renderer}"]
        out.extend(n for n in self.notes if n.startswith(("model ", "material:")))
        if self.solver is not None:
            out.append("solver: " + self.solver.summary().splitlines()[0])      # the per-level rows: -v
        out.append(f"time: frame {self.frame_seconds:.2f} s = {times} s" + (f"; set-up {t['setup']:.2f} s" if "setup" in t
                                                                           else "") + (f"; pass 2: {why[0]}" if why else ""))
        out.extend(self._clamped_lines())
        return out

    def as_dict(self) -> dict[str, Any]:
        """The full report as plain JSON-ready values (the render's sidecar file)."""
        return {"renderer": self.renderer, "nodes": self.nodes, "boundary_nodes": self.boundary_nodes,
                "image_size": list(self.image_size), "model": self.model,
                "passes": [{k: (float(v) if isinstance(v, float) else v) for k, v in p.items()} for p in self.passes],
                "seconds": {k: float(v) for k, v in self.seconds.items()},
                "frame_seconds": float(self.frame_seconds),
                "solver": self.solver.summary() if self.solver is not None else None,
                "clamped_vertices": int(self.clamped_vertices), "clamped_deep": int(self.clamped_deep),
                "clamped_depth": float(self.clamped_depth), "notes": list(self.notes),
                "warnings": list(self.warnings), "report": self.lines()}
