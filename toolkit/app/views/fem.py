"""Rerun recording of an association-model run (``knee fem``).

The recording is opened (file sink) before the first step and written as the run goes, so a run that stops
(divergence, Ctrl-C) still leaves the recording of every step up to that point. Entities (model frame, mm):

* ``knee/grid``: the soft-tissue grid's edges; ``knee/femur``, ``knee/tibia``, ``knee/skin``: the bone and
  skin surfaces carried by their mapped grid nodes;
* ``knee/depth``: the depth points (registered to the model); ``knee/truth/...``: the true bones, when
  the case has a truth; ``knee/surface_forces``: arrows from the skin points to their depth targets
  (active points only); ``knee/bone_forces``: the four bone forces of the first phase;
* ``knee/errors/{femur,tibia}``: the final target-point error map as vertex colours;
* ``metrics/errors/...``: mean target point errors per bone (footprints, epiphysis) on ``step`` and
  ``sim_time``; ``metrics/surface/reference_mm`` and ``within``; ``metrics/knee/flexion_deg``;
  ``metrics/solver/cg_iterations`` and ``inverted_cells``.
"""

from __future__ import annotations

import numpy as np
import rerun as rr
import rerun.blueprint as rrb

from knee.app.experiments.cases import CaseResult, CaseTruth
from knee.foundations import recording as R
from knee.models.fem.mapping import TrilinearMapping
from knee.models.fem.scene import knee_angles


def fem_blueprint() -> rrb.Blueprint:
    return rrb.Blueprint(rrb.Horizontal(
        rrb.Spatial3DView(origin="knee", name="Association model"),
        rrb.Vertical(rrb.TimeSeriesView(origin="metrics/errors", name="Target point errors (mm)"),
                     rrb.TimeSeriesView(origin="metrics/surface", name="Reference distance (mm), within fraction"),
                     rrb.TimeSeriesView(origin="metrics/knee", name="Flexion (deg)"),
                     rrb.TimeSeriesView(origin="metrics/solver", name="Solver")),
        column_shares=[3, 2]), collapse_panels=True)


def grid_edges(cells: np.ndarray) -> np.ndarray:
    """Unique node pairs (M, 2) of the edges of hexahedral cells (E, 8)."""
    pairs = np.array([[0, 1], [1, 2], [2, 3], [3, 0], [4, 5], [5, 6], [6, 7], [7, 4],
                      [0, 4], [1, 5], [2, 6], [3, 7]])
    e = np.sort(cells[:, pairs].reshape(-1, 2), axis=1)
    return np.unique(e, axis=0)


def error_colours(d: np.ndarray, vmax: float = 10.0) -> np.ndarray:
    """RGBA (P, 4) uint8 from distances (mm): green at 0, yellow at vmax/2, red from vmax."""
    t = np.clip(np.asarray(d, float) / vmax, 0.0, 1.0)
    r = np.clip(2 * t, 0, 1)
    g = np.clip(2 - 2 * t, 0, 1)
    return np.column_stack([255 * r, 200 * g, 40 * np.ones_like(t), 255 * np.ones_like(t)]).astype(np.uint8)


class FemRecorder:
    """A step callback (``on_step`` of :func:`knee.models.fem.methods.paper_method`) writing a recording.

    Parameters
    ----------
    path : recording file (``.rrd``), written from the start
    model : the association model
    every : log the geometry every ``every`` steps (the plots get every step)
    truth : the case's truth (:func:`knee.app.experiments.cases.case_truth`), when it has one
    """

    def __init__(self, path, model, every: int = 2, truth: CaseTruth | None = None):
        self.rec = R.new_recording()
        R.save(self.rec, path, fem_blueprint())
        self.path = path
        self.model = model
        self.every = max(1, int(every))
        self.truth = truth
        rec = self.rec
        rec.log("knee", rr.ViewCoordinates.RIGHT_HAND_Y_UP, static=True)
        self.edges = grid_edges(model.grid.cells)
        self.maps = {"femur": TrilinearMapping(model.grid, model.femur_surface.vertices),
                     "tibia": TrilinearMapping(model.grid, model.tibia_surface.vertices),
                     "skin": TrilinearMapping(model.grid, model.skin_vertices)}
        self.faces = {"femur": np.asarray(model.femur_surface.faces, np.uint32),
                      "tibia": np.asarray(model.tibia_surface.faces, np.uint32),
                      "skin": np.asarray(model.skin_faces, np.uint32)}
        if truth is not None:
            for name, mesh in truth.meshes.items():
                R.log_mesh(rec, f"knee/truth/{name}", mesh, (120, 160, 235, 140))
            self.tmaps = (TrilinearMapping(model.grid, truth.targets.femur),
                          TrilinearMapping(model.grid, truth.targets.tibia))
        self._depth_logged = False
        self.last_step = -1

    def __call__(self, k, phase, model, surf, bone) -> None:
        rec = self.rec
        s = model.solver
        rec.set_time("step", sequence=int(k))
        rec.set_time("sim_time", duration=float(s.time))
        x = s.x
        if not self._depth_logged and surf is not None:
            d = surf.depth[:: max(1, len(surf.depth) // 40000)]
            rec.log("knee/depth", rr.Points3D(d.astype(np.float32), colors=[(90, 170, 255)], radii=[0.6]),
                    static=True)
            self._depth_logged = True
        if k % self.every == 0:
            seg = x[self.edges].astype(np.float32)
            rec.log("knee/grid", rr.LineStrips3D(list(seg), colors=[(150, 150, 150)], radii=[0.15]))
            for name in ("femur", "tibia", "skin"):
                col = R.BONE_COLOURS[name]
                rec.log(f"knee/{name}", rr.Mesh3D(vertex_positions=self.maps[name].apply(x).astype(np.float32),
                                                  triangle_indices=self.faces[name], albedo_factor=col))
            if phase == "surface" and surf.active.any():
                p = surf.map.apply(x)[surf.active]
                _, j = surf.tree.query(p)
                rec.log("knee/surface_forces", rr.Arrows3D(origins=p.astype(np.float32),
                                                           vectors=(surf.depth[j] - p).astype(np.float32),
                                                           colors=[(255, 120, 40)], radii=[0.25]))
            else:
                rec.log("knee/surface_forces", rr.Clear(recursive=False))
            if phase == "bone" and bone.directions:
                pf, pt = bone.femur.bone_positions(x), bone.tibia.bone_positions(x)
                fossa = pf[bone.fossa].mean(0)
                pts = [pf[bone.shaft_f].mean(0), fossa, fossa, pt[bone.shaft_t].mean(0)]
                vec = [bone.directions[n] * 30.0 * (bone.F[i] > 0) for i, n in enumerate(("F1", "F2", "F3", "F4"))]
                rec.log("knee/bone_forces", rr.Arrows3D(origins=np.array(pts, np.float32), vectors=np.array(vec, np.float32),
                                                        labels=["F1", "F2", "F3", "F4"], colors=[(220, 40, 40)]))
            else:
                rec.log("knee/bone_forces", rr.Clear(recursive=False))
        rec.log("metrics/knee/flexion_deg", rr.Scalars(knee_angles(model, x)[0]))
        if phase == "surface":
            rec.log("metrics/surface/reference_mm", rr.Scalars(surf.reference))
            rec.log("metrics/surface/within", rr.Scalars(surf.within_fraction))
        if self.truth is not None:
            truth = self.truth
            for i, (bone_name, true, fp) in enumerate((("femur", truth.femur, truth.targets.femur_footprints),
                                                        ("tibia", truth.tibia, truth.targets.tibia_footprints))):
                # the model frame stands for the world here: the registration moves it by the noise only
                d = np.linalg.norm(self.tmaps[i].apply(x) - true, axis=1)
                rec.log(f"metrics/errors/{bone_name}_footprints", rr.Scalars(float(d[fp].mean())))
                rec.log(f"metrics/errors/{bone_name}_epiphysis", rr.Scalars(float(d.mean())))
        if s.last_info is not None:
            rec.log("metrics/solver/cg_iterations", rr.Scalars(float(s.last_info.iterations)))
        rec.log("metrics/solver/inverted_cells", rr.Scalars(float(model.inverted_cells)))
        self.last_step = k

    def finish(self, result: CaseResult | None = None, message: str | None = None) -> None:
        """Final error maps (vertex colours on the estimated target points) and a closing note."""
        rec = self.rec
        if result is not None and result.errors is not None:
            for bone_name, points in result.estimated_targets().items():
                rec.log(f"knee/errors/{bone_name}", rr.Points3D(points.astype(np.float32),
                                                              colors=error_colours(result.errors.bone(bone_name).distances),
                                                              radii=[1.0]), static=True)
        if message:
            rec.log("log", rr.TextLog(message), static=True)
        R.close(rec)  # writes the file's footer
