"""The search's fitness on the visibility database, and the exact evaluation of one network."""
from __future__ import annotations

import os

import numpy as np
from scipy.spatial import cKDTree

from calibration.camera import Intrinsics
from planning import kernels
from planning.evolution import Evaluation
from planning.planner.options import PlannerOptions
from planning.stations import ViewingSphere
from planning.sparse_info import SparseInfo
from planning.uncertainty import NetworkEval, _dedupe, covariance_for_network, criterion, evaluate_networks
from planning.visibility import VisibilityDB, VisibilityOptions, compute_visibility

_IU = (np.array([0, 0, 0, 1, 1, 2]), np.array([0, 1, 2, 1, 2, 2]))


class _Problem:
    """Evaluates populations on the visibility database (see :mod:`planning.planner`)."""

    def __init__(self, db: VisibilityDB, info: np.ndarray, vis: np.ndarray, valid: np.ndarray,
                 options: PlannerOptions, required: np.ndarray | None):
        self.db, self.info, self.vis = db, info, vis
        self.opt = options
        self.required = required
        #: "criterion" (fixed size), "ratio" (max sigma / required), "count_ratio" (front)
        self.objective = "criterion" if options.mode == "fixed" else "count_ratio"
        self.valid_idx = np.flatnonzero(valid)
        tree = cKDTree(db.eyes[valid])
        _, nearest_valid = tree.query(db.eyes)
        self.repair = np.where(valid, np.arange(len(valid)), self.valid_idx[nearest_valid])
        self._bits = None  # the candidates' visibility as bitsets (the linking rule), made when first needed

    def snap(self, genes: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Candidate index of each station after correction, and whether it was corrected."""
        idx = self.db.nearest(genes)
        fixed = self.repair[idx]
        return fixed, fixed != idx

    def __call__(self, genes: np.ndarray, bits: np.ndarray) -> Evaluation:
        genes = genes.copy()
        idx, corrected = self.snap(genes)
        genes[corrected] = self.db.genes[idx[corrected]]
        stations = np.where(bits, idx, -1)
        if isinstance(self.info, SparseInfo) and (self.objective != "criterion" or self.opt.criterion == "worst"):
            value, violation = self._fitness(stations)
            violation += self.unlinked(stations)
            if self.objective == "criterion" or self.objective == "ratio":
                objectives = value[:, None]
            else:
                objectives = np.column_stack([bits.sum(axis=1).astype(float), value])
            return Evaluation(objectives, violation, genes, bits)
        ev = evaluate_networks(self.info, stations, self.opt.min_rays, visible=self.vis)
        violation = _violation(ev) + self.unlinked(stations)
        if self.objective == "criterion":
            objectives = criterion(ev, self.opt.criterion, penalty=0.0)[:, None]
        else:
            ratio = np.max(np.where(ev.sufficient, ev.sigma / self.required, 0.0), axis=1)
            if self.objective == "ratio":
                objectives = ratio[:, None]
            else:
                objectives = np.column_stack([bits.sum(axis=1).astype(float), ratio])
        return Evaluation(objectives, violation, genes, bits)


    def unlinked(self, stations: np.ndarray) -> np.ndarray:
        """(p,) float weakly linked stations of each network ``stations: (p, k)``: outside its largest block linked
        by ``link_targets`` common targets, or (``sole_links``) alone linking a part of it; 0 when the option is off
        (planning.kernels.unlinked_stations)."""
        if self.opt.link_targets <= 0:
            return np.zeros(len(stations))
        if self._bits is None:
            self._bits = kernels.pack_rows(self.vis)
        return kernels.count_unlinked(self._bits, _dedupe(stations), self.opt.link_targets, self.opt.sole_links)

    def _fitness(self, stations: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(p,) worst sigma (or max sigma / required) and violation of networks ``stations: (p, k)``, straight
        from the sparse information (planning.kernels.population_fitness: the values of evaluate_networks +
        criterion + _violation, bit for bit, with no population x targets array)."""
        st = _dedupe(stations)
        info, n = self.info, self.info.shape[1]
        kind = 0 if self.objective == "criterion" else 2
        req = np.ones(1) if kind == 0 else np.asarray(self.required, dtype=float)
        p = len(st)
        value, violation, short = np.empty(p), np.empty(p), np.empty(p, dtype=np.int64)

        def run(lo: int, hi: int) -> None:
            kernels.population_fitness(info.starts, info.ends, info.indices, info.data, st[lo:hi], n,
                                       self.opt.min_rays, kind, req, value[lo:hi], violation[lo:hi], short[lo:hi])

        kernels.in_two(p, run, min_size=2 if (os.cpu_count() or 1) > 1 else p + 1)
        return value, violation


def _violation(ev: NetworkEval) -> np.ndarray:
    """(p,) shortfall of rays summed over targets, plus one per target with singular geometry."""
    short = np.maximum(ev.min_rays - ev.n_rays, 0).sum(axis=1)
    singular = np.count_nonzero(~ev.sufficient & (ev.n_rays >= ev.min_rays), axis=1)
    return (short + singular).astype(float)


def _exact(part, intr: Intrinsics, options: PlannerOptions, vis_opts: VisibilityOptions, genes: np.ndarray,
           sphere: ViewingSphere, cols: np.ndarray) -> dict:
    """Fresh ray casting and float64 covariance for one network; scored like the search."""
    T = sphere.poses(genes)
    visible = compute_visibility(part, intr, T, vis_opts, backend=options.backend)
    cov, n_rays = covariance_for_network(
        intr, T, part.targets.xyz, visible, options.image_sigma(), min_rays=options.min_rays
    )
    c6 = cov[:, _IU[0], _IU[1]][cols][None]
    sig = np.sqrt(np.trace(cov, axis1=1, axis2=2))[cols][None]
    ok = np.isfinite(sig)
    ev = NetworkEval(cov6=c6, sigma=np.where(ok, sig, np.inf), n_rays=n_rays[cols][None], sufficient=ok,
                     min_rays=options.min_rays)
    unlinked = 0.0
    if options.link_targets > 0:
        v = visible[:, cols]
        unlinked = float(kernels.count_unlinked(kernels.pack_rows(v), np.arange(len(v))[None], options.link_targets,
                                                options.sole_links)[0])
    return {"T": T, "visible": visible, "cov": cov, "n_rays": n_rays, "violation": float(_violation(ev)[0]),
            "unlinked": unlinked, "score": float(criterion(ev, options.criterion, penalty=0.0)[0]),
            "sigma": np.where(ok, sig, np.inf)[0]}
