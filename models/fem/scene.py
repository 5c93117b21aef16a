"""The association model of a knee (seed 000): grid + embedded bones + springs + contact.

Built from a :class:`~knee.models.fem.anatomy.KneeAnatomy` (any femur, tibia and skin surfaces in the
femur's anatomical frame, at the scanned pose): :func:`build_knee_model`. The phantom of a parameter set
is one such anatomy (:func:`phantom_anatomy`, at extension; :func:`build_association_model`). Defaults
are the paper's: soft tissue E = 1 MPa, nu = 0.3; bone E = 1500 MPa, nu = 0.3; collateral springs
1000 N/mm with rest length at the scanned pose; bone-bone penalty within 10 mm; dt = 0.05 s.
"""

from __future__ import annotations

import copy
from dataclasses import dataclass, field, fields, replace

import numpy as np
import scipy.sparse as sp
import trimesh

from knee.foundations.conventions import (
    joint_to_pose,
    matrix_to_cardan,
    transform_points,
)
from knee.foundations.errors import KneeInputError
from knee.foundations.geometry import least_varying_pair, rigid_register
from knee.foundations.surfaces import closed_surface
from knee.models.fem.anatomy import KneeAnatomy
from knee.models.fem.bones import tetrahedralize_to_count
from knee.models.fem.elements import nearest_rotations
from knee.models.fem.fields import (
    GridElasticity,
    MappedBoneElasticity,
    MappedPenaltyContact,
    MappedSprings,
)
from knee.models.fem.grid import GRID_MARGIN_MM, PAPER_CELLS_ACROSS, build_grid
from knee.models.fem.integrator import ImplicitEuler
from knee.models.fem.mapping import TrilinearMapping
from knee.models.mechanism.solver import Mechanism
from knee.models.phantom import Phantom, build_phantom

#: ``FemSettings.n_across = "knee"`` (the default): cells across the limb's anteroposterior axis (x) of about
#: this fraction of the femur's distal width, and the paper's :data:`PAPER_CELLS_ACROSS` across it (z) and at
#: least that along x (:func:`knee_sized_across`).
KNEE_CELL_WIDTHS = 1.0 / 6.0
#: The most cells along x a grid sized by the knee takes (:func:`knee_sized_across`): a skin box four femoral
#: widths deep; a leg's is about two and a half.
KNEE_SIZED_MOST = 24

SOFT_DENSITY = 1.0e-9   # tonne/mm^3 (1000 kg/m^3)
BONE_DENSITY = 1.9e-9   # tonne/mm^3


@dataclass
class FemSettings:
    """Settings of the association model (mm, MPa, N/mm, s). ``n_across`` cells across x and z (one count
    for both, or a pair (x, z): x is the femur frame's anteroposterior axis, z its medio-lateral one);
    ``element_size`` along the limb, graded down to ``joint_size`` within ``joint_half_width`` of the joint
    line (``n_along`` instead gives a uniform grid, e.g. the paper's 300); ``shaft_length`` of the phantom
    bones; ``cartilage`` set-back of the articular surfaces; materials, collateral spring stiffness,
    contact penalty and reach, time step and Rayleigh damping; ``bone_tets`` the target element count;
    ``n_across="knee"`` (the default) sizes x by the knee (:func:`knee_sized_across`; the model's settings then
    carry the pair it used; the paper's 7 x 7 is ``n_across=7``); ``grid_offset`` another placement of the same
    grid (:func:`knee.models.fem.grid.build_grid`'s ``offset``); ``soft_element`` the tissue cells' stiffness
    (:data:`knee.models.fem.elements.HEX_ELEMENTS`: the paper's ``"trilinear"``, or ``"incompatible"``, which
    bends without spurious shear). These two measured on the honest benchmark and left at the paper's
    (BENCHMARKS.md)."""

    n_across: int | tuple | str = "knee"
    element_size: float = 18.0
    joint_size: float = 3.0
    joint_half_width: float = 15.0
    shaft_length: float = 100.0
    cartilage: float = 2.5
    n_along: int | None = None
    soft_E: float = 1.0
    soft_nu: float = 0.3
    bone_E: float = 1500.0
    bone_nu: float = 0.3
    spring_k: float = 1000.0
    contact_k: float = 50.0
    contact_distance: float = 10.0
    dt: float = 0.05
    rayleigh_mass: float = 0.1
    rayleigh_stiffness: float = 0.1
    bone_tets: tuple = (400, 700)
    grid_offset: float = 0.0
    soft_element: str = "trilinear"


@dataclass
class AssociationModel:
    """The assembled model: the grid, its force fields, the integrator, and the surfaces it carries
    (skin vertices (S, 3) and faces at extension, femur and tibia surfaces at rest, femur frame)."""

    grid: object
    femur: MappedBoneElasticity
    tibia: MappedBoneElasticity
    springs: MappedSprings
    contact: MappedPenaltyContact
    soft: GridElasticity
    solver: ImplicitEuler
    skin_vertices: np.ndarray
    skin_faces: np.ndarray
    femur_surface: object
    tibia_surface: object
    settings: FemSettings = field(default_factory=FemSettings)
    anatomy: KneeAnatomy | None = None
    phantom: object = None  # the phantom the anatomy came from, if it did (its skin parts pose the prior's skin)
    joint_y: float = 0.0
    #: grid cells inverted at the last check of the state (:func:`knee.models.fem.methods.check_state`)
    inverted_cells: int = 0
    #: elements dropped, and grid nodes held for want of any element, when a prior's initialisation made
    #: its configuration the reference (:func:`knee.models.fem.methods.initialise_from_prior`)
    inverted_at_init: int = 0
    isolated_at_init: int = 0
    #: grid nodes left free at that reference with no soft cell around them (tied to the tissue only through
    #: the bone nodes embedded near them); None before one
    bone_only_nodes: np.ndarray | None = None
    #: the springs that tie those nodes to their neighbours (:func:`knee.models.fem.methods.make_reference`)
    tethers: object = None
    _thigh: tuple | None = field(default=None, repr=False)
    #: the model as built (its mechanics: elements, fields, solver), for :meth:`reset`
    _pristine: object = field(default=None, repr=False)

    #: What the methods never change: shared with the pristine copy, not copied.
    _SHARED = ("grid", "skin_vertices", "skin_faces", "femur_surface", "tibia_surface", "settings", "anatomy",
               "phantom")

    def __post_init__(self):
        self._pristine = self._copied(self)

    def _copied(self, source: "AssociationModel") -> "AssociationModel":
        memo = {id(getattr(source, name)): getattr(self, name) for name in self._SHARED}
        memo[id(source._pristine)] = None
        return copy.deepcopy(source, memo)

    def reset(self) -> None:
        """Put the model's mechanics back as built. A method makes the configuration it poses the tissue's and
        the bones' stress-free reference (dropping the elements inverted there, holding nodes left without
        any), so a model that has run one would start the next from there: the methods call this first, and
        a model gives the same answer however many times, and after whatever, it has run (tested). The
        solver's settings (:data:`ImplicitEuler.SETTINGS`: its factor backend, tolerance, ...) stay as they are
        now. Costs a copy of the mechanics (about 10 ms); the grid, the surfaces and the anatomy are shared,
        not copied."""
        if self._pristine is None:
            return
        fresh = self._copied(self._pristine)
        for name in type(self.solver).SETTINGS:  # the solver's settings as they are now (e.g. its factor backend)
            setattr(fresh.solver, name, getattr(self.solver, name))
        for f in fields(self):
            if f.name != "_pristine":
                setattr(self, f.name, getattr(fresh, f.name))

    @property
    def tibia_pose(self) -> np.ndarray:
        """The tibia's frame in the model (femur) frame at rest, (4, 4)."""
        return self.anatomy.tibia_pose

    @property
    def thigh_from(self) -> float:
        """Where the thigh region starts (model frame y, mm; :class:`KneeAnatomy`)."""
        return self.anatomy.thigh_from

    @property
    def x(self):
        """The grid's node positions (N, 3), mm, model (femur) frame."""
        return self.solver.x

    def posed_skin_vertices(self) -> np.ndarray:
        """The skin's vertices (V, 3), mm, model frame, where the grid's present displacements carry them."""
        return TrilinearMapping(self.grid, self.skin_vertices).apply(self.solver.x)

    def thigh_samples(self) -> tuple[np.ndarray, np.ndarray]:
        """Points spread densely over the model's thigh skin (the skin's vertices are ~15 mm apart) and
        their faces' normals, (P, 3) each; sampled once per model (the skin at extension does not change)."""
        if self._thigh is None:
            skin = trimesh.Trimesh(self.skin_vertices, self.skin_faces, process=False)
            dense, face = trimesh.sample.sample_surface(skin, 30000, seed=0)
            keep = dense[:, 1] > self.thigh_from
            self._thigh = (dense[keep], skin.face_normals[face[keep]])
        return self._thigh


def isometric_lateral_pair(mech: Mechanism, femur_vertices, tibia_vertices, T0, width: float,
                           angles_deg=range(0, 121, 10)):
    """Femur and tibia surface points (lateral epicondyle region: the lateral 0.15 ``width`` of the femur
    within 0.3 ``width`` of the epicondyles' level, the frame's y = 0; the lateral proximal tibia 0.3-0.75
    ``width`` below its top) whose distance varies least when the tibia follows the mechanism; tibia points
    given at the rest pose ``T0`` (4, 4). Vectorised over all pairs and angles."""
    fv, tv = np.asarray(femur_vertices), np.asarray(tibia_vertices)
    yj = float(np.max(tv[:, 1]))
    cf = fv[(fv[:, 2] > fv[:, 2].max() - 0.15 * width) & (np.abs(fv[:, 1]) < 0.3 * width)]
    ct = tv[(tv[:, 2] > tv[:, 2].max() - 0.15 * width) & (tv[:, 1] < yj - 0.3 * width) & (tv[:, 1] > yj - 0.75 * width)]
    if not len(cf) or not len(ct):
        raise KneeInputError("no lateral epicondyle or lateral proximal tibia region for the lateral collateral "
                             "spring; give the LCL's insertions")
    cf = cf[:: max(1, len(cf) // 150)]
    ct = ct[:: max(1, len(ct) // 150)]
    al = [a for a in angles_deg if mech.in_range(np.radians(a))]
    poses = joint_to_pose(mech.sweep(np.radians(np.asarray(al, float))).tf) @ np.linalg.inv(T0)
    i, j, _, _ = least_varying_pair(cf, ct, poses)
    return cf[i], ct[j]


def lumped_mass(grid, bones, soft_density=SOFT_DENSITY, bone_density=BONE_DENSITY) -> np.ndarray:
    """Nodal masses (N,): each grid cell's mass (volume x inside fraction) split over its 8 nodes, plus
    each bone tetrahedron's mass split over its 4 nodes and carried to the grid by J^T (row lumping)."""
    vol = grid.cell_volumes * grid.weights
    m = np.bincount(grid.cells.ravel(), weights=np.repeat(soft_density * vol / 8, 8), minlength=grid.n_nodes)
    for b in bones:
        p = b.el.X[b.el.cells]
        tv = np.abs(np.einsum("ij,ij->i", np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]), p[:, 3] - p[:, 0])) / 6
        mb = np.bincount(b.el.cells.ravel(), weights=np.repeat(bone_density * tv / 4, 4), minlength=len(b.el.X))
        m += b.map.J.T @ mb
    return m


def bone_cell_masks(grid, femur, tibia):
    """(N,) bool masks of the grid nodes of the cells holding each bone's nodes (nodes of cells holding
    both bones excluded)."""
    out = []
    for bone in (femur, tibia):
        m = np.zeros(grid.n_nodes, bool)
        m[grid.cells[np.unique(bone.map.cell)].ravel()] = True
        out.append(m)
    both = out[0] & out[1]
    return out[0] & ~both, out[1] & ~both


def node_rotations(grid, soft, femur, tibia):
    """The rotation of the material around each grid node, for the warped preconditioner.

    Nodes that carry bone (the nodes of the cells holding a bone's nodes) turn with the bones: the bones'
    best-fit rotations, averaged with the weights by which each bone's nodes load the node (its column
    sums of the embedding; a node of a cell holding both bones blends the two). The bones are about a
    thousand times stiffer than the tissue, so a wrong rotation at even a few of these nodes spoils the
    preconditioner: measured on the prior's 120 deg case, the four nodes shared by femur and tibia given a
    tissue cell's rotation took a kept factorisation from about 33 to 130 iterations per step. Elsewhere,
    the average of the rotations of the live grid cells around the node (its nearest rotation).

    Returns the function ``rotations(x)``: grid positions (N, 3) -> rotations (N, 3, 3)."""
    n = grid.n_nodes
    weights = [np.asarray(b.map.J.sum(axis=0)).ravel() for b in (femur, tibia)]
    bone = (weights[0] + weights[1]) > 0
    # node-cell incidence, rows: nodes; the cells' rotations are summed per node by one sparse product
    cells = grid.cells
    incidence = sp.csr_matrix((np.ones(cells.size), (cells.ravel(), np.repeat(np.arange(len(cells)), 8))),
                              shape=(n, len(cells)))
    tissue = np.nonzero(~bone)[0]
    inc_t = incidence[tissue]

    def rotations(x):
        R = np.empty((n, 3, 3))
        alive = soft.el.alive
        S = (inc_t @ (soft.el.R.reshape(-1, 9) * alive[:, None])).reshape(-1, 3, 3)
        none = (inc_t @ alive.astype(float)) == 0  # every cell around it dropped: any cell will do
        if none.any():
            S[none] = (inc_t[none] @ soft.el.R.reshape(-1, 9)).reshape(-1, 3, 3)
        R[tissue] = nearest_rotations(S)
        Rb = [best_fit_rotation(b.el.X, b.bone_positions(x)) for b in (femur, tibia)]
        wf, wt = weights[0][bone], weights[1][bone]
        Rn = np.where((wt == 0)[:, None, None], Rb[0], Rb[1])  # nodes carrying one bone: its rotation
        both = (wf > 0) & (wt > 0)
        if both.any():
            Rn[both] = nearest_rotations(wf[both, None, None] * Rb[0] + wt[both, None, None] * Rb[1])
        R[bone] = Rn
        return R

    return rotations


def phantom_anatomy(mech: Mechanism, settings: FemSettings | None = None) -> tuple[KneeAnatomy, Phantom]:
    """The anatomy of ``mech``'s phantom at full extension (0 deg flexion), in the femur frame, with the
    mechanism's MCL as the medial collateral insertions (the LCL left to :func:`build_knee_model`), and the
    phantom itself."""
    s = settings or FemSettings()
    ph = build_phantom(mech.params, shaft_length=s.shaft_length, cartilage=s.cartilage)
    T = joint_to_pose(mech.solve(0.0)[0])
    mcl = mech.params.link("mcl")
    anatomy = KneeAnatomy(ph.femur, ph.tibia.copy().apply_transform(T), ph.skin(T), T,
                          mcl=np.vstack([mcl.femur, transform_points(T, mcl.tibia[None, :])[0]]),
                          name=mech.params.name)
    return anatomy, ph


def knee_sized_across(skin_bounds, width: float, cell_widths: float = KNEE_CELL_WIDTHS,
                      least: int = PAPER_CELLS_ACROSS, most: int = KNEE_SIZED_MOST) -> tuple[int, int]:
    """The grid's cells across the limb (x, z) sized by the knee: along the anteroposterior axis x, as many as
    make cells of about ``cell_widths`` of the femur's distal ``width`` (mm) over the grid's box (the skin's,
    ``skin_bounds``, (2, 3), mm, the femur frame, widened by the grid's margin on each side), at least
    ``least`` and at most ``most`` (a skin box many femoral widths deep would otherwise ask for a grid whose
    matrix grows with the square of the count); across it, z, ``least``.

    Why by the knee: the paper's count is per skin box, so the cells at the knee grow with how much of the leg
    the scan holds and how thick the thigh is (a whole leg's skin spans twice or more its femoral width across
    x, and 7 cells there are a third of the femur wide); sized by the knee, a scan's extent no longer sets the
    model's resolution at the joint. Why x alone: what a coarse grid gets wrong on a real leg is the femur's
    place along x (the posed knee's front too thick by a fraction of a cell), and cells of about a sixth of the
    femoral width along x remove most of it (BENCHMARKS.md, "A finer grid on request").

    The model's default since it was measured on the honest benchmark's truth with the refined skin
    (BENCHMARKS.md, "The grid sized by the knee made the default"), against 7 x 7 at 0-1 mm skin mismatch:
    per case 0.09 mm better on the five seeds the method's choices were made on (se 0.05; the median 2.20 ->
    2.30 mm), 0.11 held out (se 0.05; 2.51 -> 2.35) and 0.10 on lenhart2015 (se 0.04; 1.93 -> 1.79); the
    Visible Human (14 x 7) and lenhart2015 (15 x 7) gain, the phantom (9 x 7) loses 0.05-0.08 mm a case; the
    flexion within 2 deg in 240, 230 and 103 views against 232, 227 and 92. On four seeds' sets built after
    the choice: 0.07 mm a case better (se 0.05; the Visible Human 0.22, the phantom 0.08 worse). It costs 1.22
    times 7 x 7's time a case."""
    lo, hi = np.asarray(skin_bounds, float)
    if not width > 0:
        raise KneeInputError(f"the femur's width must be positive to size the grid by the knee, got {width}")
    nx = max(int(least), int(round((hi[0] - lo[0] + 2.0 * GRID_MARGIN_MM) / (cell_widths * width))))
    nx = min(nx, max(int(most), int(least)))
    return nx, int(least)


def build_knee_model(anatomy: KneeAnatomy, settings: FemSettings | None = None, prior: Mechanism | None = None,
                     phantom: Phantom | None = None) -> AssociationModel:
    """The association model of a knee's surfaces (see the module docstring), in the femur frame at the
    scanned pose.

    The collateral springs run between the anatomy's insertions; without an LCL, between the pair of
    surface points (lateral epicondyle region, lateral proximal tibia) whose distance varies least along
    ``prior``'s motion, so that the spring does not resist flexion (a prior is then required). Raises
    :class:`KneeInputError` when the bones are not inside the skin or a surface is not closed."""
    s = settings or FemSettings()
    anatomy.check()
    skin = closed_surface(anatomy.skin, "skin")
    joint_y, width = anatomy.joint_y, anatomy.width
    if isinstance(s.n_across, str):
        if s.n_across != "knee":
            raise KneeInputError(f"n_across must be a count, a pair of counts (x, z) or \"knee\", got {s.n_across!r}")
        s = replace(s, n_across=knee_sized_across(skin.bounds, width))  # the model keeps the counts it used
    grid = build_grid(skin, s.n_across, s.element_size, s.n_along, joint_y=joint_y,
                      joint_size=s.joint_size, joint_half_width=s.joint_half_width, offset=s.grid_offset)
    Xf, Tf, _ = tetrahedralize_to_count(anatomy.femur, s.bone_tets)
    Xt, Tt, _ = tetrahedralize_to_count(anatomy.tibia, s.bone_tets)
    femur = MappedBoneElasticity(grid, Xf, Tf, s.bone_E, s.bone_nu, name="femur")
    tibia = MappedBoneElasticity(grid, Xt, Tt, s.bone_E, s.bone_nu, name="tibia")
    soft = GridElasticity(grid, s.soft_E, s.soft_nu, s.soft_element)
    # collateral springs: along the insertions given; an LCL not given between the lateral surface points
    # whose distance varies least over the prior's motion (so the spring does not resist flexion)
    fv, tv = np.asarray(anatomy.femur.vertices), np.asarray(anatomy.tibia.vertices)
    lcl = anatomy.lcl
    if lcl is None:
        if prior is None:
            raise KneeInputError("the model needs the LCL's insertions, or a prior mechanism to place the lateral "
                                 "collateral spring")
        lcl = np.vstack(isometric_lateral_pair(prior, fv, tv, anatomy.tibia_pose, width))
    pairs = [p for p in (anatomy.mcl, lcl) if p is not None]
    springs = MappedSprings(grid, np.vstack([p[0] for p in pairs]), np.vstack([p[1] for p in pairs]), s.spring_k)
    fpts, tpts = anatomy.contact_points()
    contact = MappedPenaltyContact(grid, fpts, tpts, s.contact_k, s.contact_distance)
    mass = lumped_mass(grid, [femur, tibia])
    # the thigh is held (as in a leg holder) around the proximal femoral shaft: grid nodes from one
    # cell below the top of the femur mesh upwards are fixed
    fixed = grid.X[:, 1] >= grid.axes[1][np.searchsorted(grid.axes[1], Xf[:, 1].max()) - 1]
    solver = ImplicitEuler(grid.X, mass, [soft, femur, tibia, springs, contact], s.dt, s.rayleigh_mass,
                           s.rayleigh_stiffness, fixed=fixed, node_rotations=node_rotations(grid, soft, femur, tibia))
    solver.prepare()
    return AssociationModel(grid=grid, femur=femur, tibia=tibia, springs=springs, contact=contact, soft=soft,
                            solver=solver, skin_vertices=np.asarray(skin.vertices), skin_faces=np.asarray(skin.faces),
                            femur_surface=anatomy.femur, tibia_surface=anatomy.tibia, settings=s, anatomy=anatomy,
                            phantom=phantom, joint_y=joint_y)


def build_association_model(mech: Mechanism, settings: FemSettings | None = None) -> AssociationModel:
    """The model of ``mech``'s phantom at full extension (0 deg flexion), in the femur frame
    (:func:`phantom_anatomy`, :func:`build_knee_model`)."""
    anatomy, ph = phantom_anatomy(mech, settings)
    return build_knee_model(anatomy, settings, prior=mech, phantom=ph)


def best_fit_rotation(rest: np.ndarray, current: np.ndarray) -> np.ndarray:
    """Rotation R (3, 3) of the least-squares rigid fit of ``rest`` onto ``current`` (Kabsch)."""
    return rigid_register(rest, current)[0][:3, :3]


def knee_angles(model: "AssociationModel", x=None):
    """(flexion_deg, femur_tibia_angle_deg) of the FEM bones at grid positions ``x``: the flexion is the
    Cardan flexion of the tibia's anatomical frame relative to the femur's (the bones' best-fit rotations
    from rest composed with the scanned pose); the femur-tibia angle is the angle between the femur's
    proximal axis and the tibia's distal axis (180 when aligned), the quantity the paper's bone-force
    phase drives below 100 degrees."""
    x = model.x if x is None else x
    Rf = best_fit_rotation(model.femur.el.X, model.femur.bone_positions(x))
    Rt = best_fit_rotation(model.tibia.el.X, model.tibia.bone_positions(x))
    R_scan = model.tibia_pose[:3, :3]
    flex = np.degrees(matrix_to_cardan(Rf.T @ Rt @ R_scan)[0])
    between = np.degrees(np.arccos(np.clip((Rf @ [0, 1, 0]) @ (Rt @ R_scan @ [0, -1, 0]), -1, 1)))
    return float(flex), float(between)
