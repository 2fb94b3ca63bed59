"""The planned network and its plan.json document: :class:`NetworkPlan`."""
from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from calibration.camera import Intrinsics
from calibration.errors import InputError
from planning.stations import N_GENES


@dataclass
class NetworkPlan:
    """A planned network and its predicted precision (the content of plan.json).

    Attributes:
        seed: the seed the search's generator was made from (None if not given).
        criterion: the criterion minimised; mode: "fixed" | "cheapest".
        intrinsics: the camera; sigma_px: image noise assumed (pixels).
        min_rays, incidence_max_rad: the constraints planned for.
        station_ids: (k,) str; part_from_cam: (k, 4, 4); genes: (k, N_GENES).
        target_ids: (n,) str; xyz, normals: (n, 3).
        cov: (n, 3, 3) predicted covariance (m^2), exact for the final stations; nan
            where a target is measured by fewer than ``min_rays`` stations.
        n_rays: (n,) int; seen_by: per target the ids of the stations that measure it.
        predicted_sigma_max_m, predicted_sigma_mean_m: over the targets planned for (those
            in ``unmeasurable_target_ids`` excluded), sigma = sqrt(trace(cov)).
        history: one dict per generation (best, mean, n_active, n_feasible, phase: "search"
            or "refine <k>", step: running index over the phases, ...).
        pareto_front: "cheapest": [{n_stations, sigma_ratio_max, phase}] of the front
            (phase "front") and of the refining searches (phase "refine"; inf if infeasible).
        required_sigma_m: (n,) the requirement in "cheapest" mode, else None.
        unmeasurable_target_ids: targets left out of the search (allow_unmeasurable).
        timing: seconds per stage.
        search: summary (stopped_because, n_evaluations, which poses were kept, ...).
        scale_bars: plan.json ``scale_bars`` (:mod:`planning.scalebar`), one record per bar: its ends, their
            predicted part of the length sigma before and after, the stations added for them and why; empty
            without a bar. With exactly one bar plan.json also carries it as ``scale_bar`` (the single-bar record
            older readers know).
    """

    seed: int | None
    criterion: str
    mode: str
    intrinsics: Intrinsics
    sigma_px: float
    min_rays: int
    incidence_max_rad: float
    station_ids: list[str]
    part_from_cam: np.ndarray
    genes: np.ndarray
    target_ids: list[str]
    xyz: np.ndarray
    normals: np.ndarray
    cov: np.ndarray
    n_rays: np.ndarray
    seen_by: list[list[str]]
    predicted_sigma_max_m: float
    predicted_sigma_mean_m: float
    history: list[dict] = field(default_factory=list)
    pareto_front: list[dict] = field(default_factory=list)
    required_sigma_m: np.ndarray | None = None
    unmeasurable_target_ids: list[str] = field(default_factory=list)
    timing: dict = field(default_factory=dict)
    search: dict = field(default_factory=dict)
    scale_bars: list[dict] = field(default_factory=list)

    @property
    def sigma(self) -> np.ndarray:
        """(n,) sqrt(trace(cov)) per target (m), inf where not measurable."""
        s = np.sqrt(np.trace(self.cov, axis1=1, axis2=2))
        return np.where(np.isfinite(s), s, np.inf)

    def to_plan_dict(self) -> dict:
        """The plan.json document (ARCHITECTURE.md "plan.json"), JSON-ready."""
        i = self.intrinsics
        cov_list = [None if not np.all(np.isfinite(c)) else c.tolist() for c in self.cov]
        return {
            "seed": self.seed,
            "criterion": self.criterion,
            "mode": self.mode,
            "camera": {
                "fx_px": i.fx_px, "fy_px": i.fy_px, "cx_px": i.cx_px, "cy_px": i.cy_px,
                "width": i.width, "height": i.height, "sigma_px": self.sigma_px,
                "k1": i.k1, "k2": i.k2, "k3": i.k3, "p1": i.p1, "p2": i.p2,
            },
            "min_rays": self.min_rays,
            "incidence_max_rad": self.incidence_max_rad,
            "stations": [
                {"id": sid, "part_from_cam": T.tolist(), "genes": g.tolist()}
                for sid, T, g in zip(self.station_ids, self.part_from_cam, self.genes)
            ],
            "targets": [
                {
                    "id": tid, "xyz": x.tolist(), "normal": nrm.tolist(), "seen_by": list(sb),
                    "predicted_cov": c, "n_rays": int(nr),
                    **({} if self.required_sigma_m is None else {"required_sigma_m": float(self.required_sigma_m[j])}),
                }
                for j, (tid, x, nrm, sb, c, nr) in enumerate(
                    zip(self.target_ids, self.xyz, self.normals, self.seen_by, cov_list, self.n_rays)
                )
            ],
            "predicted_sigma_max_m": _json_float(self.predicted_sigma_max_m),
            "predicted_sigma_mean_m": _json_float(self.predicted_sigma_mean_m),
            "unmeasurable_target_ids": list(self.unmeasurable_target_ids),
            "history": [{k: _json_float(v) for k, v in row.items()} for row in self.history],
            "pareto_front": [{k: _json_float(v) for k, v in row.items()} for row in self.pareto_front],
            "timing": dict(self.timing),
            "search": {k: _json_float(v) for k, v in self.search.items()},
            **({"scale_bars": list(self.scale_bars)} if self.scale_bars else {}),
            **({"scale_bar": self.scale_bars[0]} if len(self.scale_bars) == 1 else {}),
        }

    @classmethod
    def from_plan_dict(cls, d: dict) -> "NetworkPlan":
        """Read a plan.json document back (extra keys, e.g. added by VALIDATE, are ignored)."""
        try:
            cam = d["camera"]
            intr = Intrinsics(
                fx_px=float(cam["fx_px"]), fy_px=float(cam["fy_px"]), cx_px=float(cam["cx_px"]),
                cy_px=float(cam["cy_px"]), width=int(cam["width"]), height=int(cam["height"]),
                **{k: float(cam.get(k, 0.0)) for k in ("k1", "k2", "k3", "p1", "p2")},
            )
            st = d["stations"]
            tg = d["targets"]
            cov = np.array([np.full((3, 3), np.nan) if t["predicted_cov"] is None else t["predicted_cov"] for t in tg],
                           dtype=float).reshape(-1, 3, 3)
            station_ids = [str(s["id"]) for s in st]
            seen_by = [[str(x) for x in t["seen_by"]] for t in tg]
            req = [t.get("required_sigma_m") for t in tg]
            return cls(
                seed=d.get("seed"),
                criterion=str(d["criterion"]),
                mode=str(d.get("mode", "fixed")),
                intrinsics=intr,
                sigma_px=float(cam["sigma_px"]),
                min_rays=int(d["min_rays"]),
                incidence_max_rad=float(d["incidence_max_rad"]),
                station_ids=station_ids,
                part_from_cam=np.array([s["part_from_cam"] for s in st], dtype=float).reshape(-1, 4, 4),
                genes=np.array([s.get("genes", [np.nan] * N_GENES) for s in st], dtype=float).reshape(-1, N_GENES),
                target_ids=[str(t["id"]) for t in tg],
                xyz=np.array([t["xyz"] for t in tg], dtype=float).reshape(-1, 3),
                normals=np.array([t["normal"] for t in tg], dtype=float).reshape(-1, 3),
                cov=cov,
                n_rays=np.array([t.get("n_rays", len(s)) for t, s in zip(tg, seen_by)], dtype=int),
                seen_by=seen_by,
                predicted_sigma_max_m=_float_back(d["predicted_sigma_max_m"]),
                predicted_sigma_mean_m=_float_back(d["predicted_sigma_mean_m"]),
                history=list(d.get("history", [])),
                pareto_front=list(d.get("pareto_front", [])),
                required_sigma_m=None if any(r is None for r in req) or not req else np.array(req, dtype=float),
                unmeasurable_target_ids=list(d.get("unmeasurable_target_ids", [])),
                timing=dict(d.get("timing", {})),
                search=dict(d.get("search", {})),
                scale_bars=list(d.get("scale_bars") or ([d["scale_bar"]] if d.get("scale_bar") else [])),
            )
        except (KeyError, TypeError, ValueError) as exc:
            raise InputError(f"plan.json is not a valid plan ({type(exc).__name__}: {exc}); re-run `cell plan`") from exc


def _json_float(v):
    if isinstance(v, (float, np.floating)):
        v = float(v)
        return v if math.isfinite(v) else None
    if isinstance(v, np.integer):
        return int(v)
    return v


def _float_back(v) -> float:
    return float("inf") if v is None else float(v)
