"""Parameters of the 1-DoF spatial parallel mechanism of the knee, and their TOML file format.

The tibio-femoral (TF) group has five links between femur and tibia (seed 002, eq. 1). Each link is
either

* ``kind = "distance"``: a rigid link of constant ``length`` between a femoral point and a tibial point.
  It models an isometric ligament fibre (ACL, PCL, MCL) and a sphere-sphere condylar contact, whose
  constraint is a rigid link between the two sphere centres: length = R_tibia + R_femur for a convex
  tibial facet, R_tibia - R_femur for a concave one; or
* ``kind = "sphere-plane"``: a femoral sphere centre whose distance to a tibial plane (point ``tibia``,
  unit ``normal``, both in the tibia frame) is the constant ``length`` (the sphere radius).

The patello-femoral (PF) group (optional) is a helical pair about an axis given by a unit direction and a
point in the femur (``axis_femur``, ``point_femur``) and in the patella (``axis_patella``,
``point_patella``), with axial translation ``lambda0 + lambda1 * theta`` (theta: the patella's rotation
about the axis from its reference pose, radians; lambda1 in mm/rad), and a rigid patellar-tendon link
(``tendon_tibia``, ``tendon_patella``, ``tendon_length``). The reference pose is taken at the knee
flexion ``reference_flexion`` (seed 002: mid-arc, 55 degrees).

All lengths in mm, points in the frame of their own bone (x anterior, y proximal, z lateral, right knee).
See README.md, "Parameter files", for the TOML layout.
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass, replace
from importlib import resources
from pathlib import Path

import numpy as np

from knee.foundations.errors import KneeInputError, ModelFileError, UnknownModelError
from knee.foundations.files import read_text

FORMAT_NAME = "knee-mechanism"
FORMAT_VERSION = 1
LINK_KINDS = ("distance", "sphere-plane")
LINK_ROLES = ("ligament", "contact")
#: Number of flat parameters per TF link: femur(3), tibia(3), normal(3), length(1).
LINK_SIZE = 10
#: Flat PF parameters: axis_f(3) point_f(3) axis_p(3) point_p(3) tendon_t(3) tendon_p(3)
#: tendon_length lambda0 lambda1 reference_flexion.
PF_SIZE = 22
N_LINKS = 5
N_PARAMS = N_LINKS * LINK_SIZE + PF_SIZE
#: A knee whose link points and lengths are all under this many mm is a file in metres.
METRES_BELOW_MM = 2.0

# The flat parameter vector's layout (:meth:`MechanismParams.to_vector`), named. Within link i's block,
# which starts at ``i * LINK_SIZE``: the femoral point, the tibial point, the plane normal and the length.
LINK_FEMUR, LINK_TIBIA, LINK_NORMAL, LINK_LENGTH = slice(0, 3), slice(3, 6), slice(6, 9), 9
#: Where the patello-femoral group starts, and its entries (absolute indices into the vector).
PF0 = N_LINKS * LINK_SIZE
PF_AXIS_FEMUR = slice(PF0, PF0 + 3)
PF_POINT_FEMUR = slice(PF0 + 3, PF0 + 6)
PF_AXIS_PATELLA = slice(PF0 + 6, PF0 + 9)
PF_POINT_PATELLA = slice(PF0 + 9, PF0 + 12)
PF_TENDON_TIBIA = slice(PF0 + 12, PF0 + 15)
PF_TENDON_PATELLA = slice(PF0 + 15, PF0 + 18)
PF_TENDON_LENGTH, PF_LAMBDA0, PF_LAMBDA1, PF_REFERENCE_FLEXION = PF0 + 18, PF0 + 19, PF0 + 20, PF0 + 21


def link_entries(i: int, part) -> slice | int:
    """Absolute index (or slice) of entry ``part`` (``LINK_FEMUR``, ...) of link ``i`` in the vector."""
    o = i * LINK_SIZE
    return slice(o + part.start, o + part.stop) if isinstance(part, slice) else o + part


@dataclass(frozen=True)
class Link:
    """One TF link.

    Attributes
    ----------
    name : str
        e.g. ``"acl"``, ``"lc"``.
    role : str
        ``"ligament"`` (can only pull) or ``"contact"`` (can only push).
    kind : str
        ``"distance"`` or ``"sphere-plane"``.
    femur, tibia : (3,) float
        Femoral point and tibial point (or a point of the tibial plane), mm, in their bone's frame.
    length : float
        Link length, or sphere-centre-to-plane distance, mm.
    normal : (3,) float or None
        Unit normal of the tibial plane (``sphere-plane`` only), tibia frame.
    femur_radius : float or None
        Radius of the femoral condyle sphere (contacts; used for geometry and contact mechanics).
    tibia_surface : str or None
        ``"convex"`` or ``"concave"`` tibial facet of a sphere-sphere contact, ``"plane"`` for a
        sphere-plane one.
    """

    name: str
    role: str
    kind: str
    femur: np.ndarray
    tibia: np.ndarray
    length: float
    normal: np.ndarray | None = None
    femur_radius: float | None = None
    tibia_surface: str | None = None

    @property
    def tibia_radius(self) -> float | None:
        """Radius of the tibial facet sphere of a sphere-sphere contact (None otherwise)."""
        if self.role != "contact" or self.kind != "distance" or self.femur_radius is None:
            return None
        if self.tibia_surface == "convex":
            return self.length - self.femur_radius
        return self.length + self.femur_radius


@dataclass(frozen=True)
class PFGroup:
    """The patello-femoral group (seed 002, eqs. 2-4). Vectors (3,) float, lengths mm, angles rad."""

    axis_femur: np.ndarray
    point_femur: np.ndarray
    axis_patella: np.ndarray
    point_patella: np.ndarray
    tendon_tibia: np.ndarray
    tendon_patella: np.ndarray
    tendon_length: float
    lambda0: float
    lambda1: float
    reference_flexion: float


@dataclass(frozen=True)
class InitialPose:
    """A TF assembly (branch) to start sweeps from: at ``flexion`` (rad), the unknowns
    ``(beta, gamma, anterior, proximal, lateral)`` (rad, mm)."""

    flexion: float
    unknowns: np.ndarray


@dataclass(frozen=True)
class MechanismParams:
    """A complete parameter set of the knee mechanism.

    Use :func:`load_model` to read one (bundled name or TOML path) and :meth:`to_toml` to write it.
    :meth:`to_vector` gives the flat vector (``N_PARAMS`` floats) the CasADi functions take;
    :func:`parameter_names` names its entries.
    """

    name: str
    links: tuple[Link, ...]
    pf: PFGroup | None = None
    initial: InitialPose | None = None
    description: str = ""
    source: str = ""
    side: str = "right"

    @property
    def kinds(self) -> tuple[str, ...]:
        """The link kinds, which fix the structure of the closure equations."""
        return tuple(link.kind for link in self.links)

    @property
    def has_pf(self) -> bool:
        return self.pf is not None

    def link(self, name: str) -> Link:
        for lk in self.links:
            if lk.name == name:
                return lk
        raise KeyError(name)

    def to_vector(self) -> np.ndarray:
        """The flat parameter vector, (N_PARAMS,) float; PF entries are zeros without a PF group."""
        v = np.zeros(N_PARAMS)
        for i, lk in enumerate(self.links):
            o = i * LINK_SIZE
            v[o:o + 3] = lk.femur
            v[o + 3:o + 6] = lk.tibia
            v[o + 6:o + 9] = lk.normal if lk.normal is not None else 0.0
            v[o + 9] = lk.length
        if self.pf is not None:
            f = self.pf
            for sl, val in ((PF_AXIS_FEMUR, f.axis_femur), (PF_POINT_FEMUR, f.point_femur),
                            (PF_AXIS_PATELLA, f.axis_patella), (PF_POINT_PATELLA, f.point_patella),
                            (PF_TENDON_TIBIA, f.tendon_tibia), (PF_TENDON_PATELLA, f.tendon_patella),
                            (PF_TENDON_LENGTH, f.tendon_length), (PF_LAMBDA0, f.lambda0), (PF_LAMBDA1, f.lambda1),
                            (PF_REFERENCE_FLEXION, f.reference_flexion)):
                v[sl] = val
        return v

    def with_vector(self, v) -> "MechanismParams":
        """A copy with the numeric values taken from a flat vector (inverse of :meth:`to_vector`)."""
        v = np.asarray(v, dtype=float)
        if v.shape != (N_PARAMS,):
            raise ValueError(f"parameter vector must have shape ({N_PARAMS},), got {v.shape}")
        links = []
        for i, lk in enumerate(self.links):
            links.append(replace(lk, femur=v[link_entries(i, LINK_FEMUR)].copy(),
                                 tibia=v[link_entries(i, LINK_TIBIA)].copy(),
                                 normal=None if lk.normal is None else v[link_entries(i, LINK_NORMAL)].copy(),
                                 length=float(v[link_entries(i, LINK_LENGTH)])))
        pf = self.pf
        if pf is not None:
            pf = PFGroup(v[PF_AXIS_FEMUR].copy(), v[PF_POINT_FEMUR].copy(), v[PF_AXIS_PATELLA].copy(),
                         v[PF_POINT_PATELLA].copy(), v[PF_TENDON_TIBIA].copy(), v[PF_TENDON_PATELLA].copy(),
                         tendon_length=float(v[PF_TENDON_LENGTH]), lambda0=float(v[PF_LAMBDA0]),
                         lambda1=float(v[PF_LAMBDA1]), reference_flexion=float(v[PF_REFERENCE_FLEXION]))
        return replace(self, links=tuple(links), pf=pf)

    def to_toml(self) -> str:
        """This parameter set in the versioned TOML format (see README.md)."""
        return dumps_toml(self)


def require_condylar_contacts(p: "MechanismParams", what: str) -> None:
    """Refuse (one line) parameters without exactly two contact links, the lateral and medial condyles
    that the phantom, the contact model, gait, osteotomy and the FEM are built on."""
    contacts = [lk.name for lk in p.links if lk.role == "contact"]
    if len(contacts) != 2:
        raise ModelFileError(f"model {p.name!r}: {what} needs exactly two condylar contact links (role = "
                             f"\"contact\"), it has {len(contacts)} ({', '.join(contacts) or 'none'})")


def parameter_names() -> list[str]:
    """Names of the entries of :meth:`MechanismParams.to_vector`, e.g. ``link0.femur.x``."""
    names = []
    for i in range(N_LINKS):
        for part in ("femur", "tibia", "normal"):
            names += [f"link{i}.{part}.{c}" for c in "xyz"]
        names.append(f"link{i}.length")
    for part in ("axis_femur", "point_femur", "axis_patella", "point_patella", "tendon_tibia",
                 "tendon_patella"):
        names += [f"pf.{part}.{c}" for c in "xyz"]
    names += ["pf.tendon_length", "pf.lambda0", "pf.lambda1", "pf.reference_flexion"]
    return names


# ----------------------------------------------------------------------------------------------
# Reading


def _fail(where: str, what: str):
    raise ModelFileError(f"{where}: {what}")


def _number(d: dict, key: str, where: str) -> float:
    if key not in d:
        _fail(where, f"missing field '{key}'")
    x = d[key]
    if isinstance(x, bool) or not isinstance(x, (int, float)):
        _fail(where, f"field '{key}' must be a number, got {x!r}")
    if not math.isfinite(x):
        _fail(where, f"field '{key}' is not finite ({x})")
    return float(x)


def _vector(d: dict, key: str, where: str, n: int = 3) -> np.ndarray:
    if key not in d:
        _fail(where, f"missing field '{key}'")
    x = d[key]
    if not isinstance(x, list) or len(x) != n:
        _fail(where, f"field '{key}' must be a list of {n} numbers, got {x!r}")
    for e in x:
        if isinstance(e, bool) or not isinstance(e, (int, float)):
            _fail(where, f"field '{key}' must be a list of {n} numbers, got {x!r}")
        if not math.isfinite(e):
            _fail(where, f"field '{key}' has a non-finite value ({e})")
    return np.array(x, dtype=float)


def _choice(d: dict, key: str, where: str, choices) -> str:
    if key not in d:
        _fail(where, f"missing field '{key}'")
    x = d[key]
    if x not in choices:
        _fail(where, f"field '{key}' must be one of {', '.join(choices)}; got {x!r}")
    return x


def _angles_to_unit(theta: float, phi: float) -> np.ndarray:
    """Seed 002 Table 1: n = [cos(phi) sin(theta), sin(phi) sin(theta), cos(theta)]."""
    return np.array([math.cos(phi) * math.sin(theta), math.sin(phi) * math.sin(theta), math.cos(theta)])


def _unit(d: dict, key: str, where: str, angle_scale: float) -> np.ndarray:
    """A unit vector given as ``key = [x, y, z]`` or ``key_angles = [theta, phi]``."""
    if key + "_angles" in d:
        th, ph = _vector(d, key + "_angles", where, 2) * angle_scale
        return _angles_to_unit(th, ph)
    v = _vector(d, key, where)
    n = np.linalg.norm(v)
    if n < 1e-12:
        _fail(where, f"field '{key}' must be a non-zero direction")
    return v if abs(n - 1.0) < 1e-14 else v / n


def _point(d: dict, key: str, where: str) -> np.ndarray:
    """A point given as [x, y, z] or, for the helical-axis points of seed 002, [x, y] with z = 0."""
    if key in d and isinstance(d[key], list) and len(d[key]) == 2:
        return np.append(_vector(d, key, where, 2), 0.0)
    return _vector(d, key, where)


def params_from_dict(data: dict, origin: str = "<dict>") -> MechanismParams:
    """Validate a parsed TOML document and build :class:`MechanismParams`.

    Raises
    ------
    ModelFileError
        One line naming the file, the field and what is wrong with it.
    """
    w = origin
    if data.get("format") != FORMAT_NAME:
        _fail(w, f"field 'format' must be \"{FORMAT_NAME}\", got {data.get('format')!r}")
    version = data.get("version")
    if version != FORMAT_VERSION:
        _fail(w, f"field 'version' must be {FORMAT_VERSION} (this toolkit's format), got {version!r}")
    units = data.get("units")
    if not isinstance(units, dict):
        _fail(w, "missing table [units] (length = \"mm\", angle = \"rad\" or \"deg\")" if units is None else
              f"'units' must be a table ([units] with length = \"mm\", angle = \"rad\" or \"deg\"), got {units!r}")
    if units.get("length") != "mm":
        _fail(w + " [units]", f"length must be \"mm\" (the toolkit's unit), got {units.get('length')!r}")
    if units.get("angle") not in ("rad", "deg"):
        _fail(w + " [units]", f"angle must be \"rad\" or \"deg\", got {units.get('angle')!r}")
    ascale = 1.0 if units["angle"] == "rad" else math.pi / 180.0
    name = data.get("name")
    if name is None:
        _fail(w, "missing field 'name'")
    if not isinstance(name, str) or not name.strip():
        _fail(w, f"field 'name' must be a non-empty string, got {name!r}")
    side = data.get("side", "right")
    if side not in ("right", "left"):
        _fail(w, f"field 'side' must be \"right\" or \"left\", got {side!r}")

    tf = data.get("tf")
    if not isinstance(tf, dict) or "links" not in tf:
        _fail(w, "missing table [tf] with its [[tf.links]]" if tf is None or isinstance(tf, dict) else
              f"'tf' must be a table with its [[tf.links]], got {tf!r}")
    raw_links = tf["links"]
    if not isinstance(raw_links, list) or len(raw_links) != N_LINKS:
        n = len(raw_links) if isinstance(raw_links, list) else 0
        _fail(w, f"[tf] needs exactly {N_LINKS} [[tf.links]] for a 1-DoF mechanism, got {n}")
    links = []
    for i, d in enumerate(raw_links):
        lw = f"{w} tf.links[{i}]"
        if not isinstance(d, dict):
            _fail(lw, f"each of tf.links must be a table ([[tf.links]]), got {d!r}")
        lname = d.get("name")
        if not isinstance(lname, str) or not lname:
            _fail(lw, "missing field 'name'" if lname is None else f"field 'name' must be a string, got {lname!r}")
        lw = f"{w} tf.links[{i}] ({lname})"
        role = _choice(d, "role", lw, LINK_ROLES)
        kind = _choice(d, "kind", lw, LINK_KINDS)
        femur = _vector(d, "femur", lw)
        tibia = _vector(d, "tibia", lw)
        length = _number(d, "length", lw)
        normal = None
        if kind == "sphere-plane":
            normal = _unit(d, "normal", lw, ascale)
            if role != "contact":
                _fail(lw, "a sphere-plane link must have role = \"contact\"")
        elif length <= 0:
            _fail(lw, f"field 'length' must be positive, got {length}")
        fr = None
        surface = None
        if role == "contact":
            if "femur_radius" in d:
                fr = _number(d, "femur_radius", lw)
                if fr <= 0:
                    _fail(lw, f"field 'femur_radius' must be positive, got {fr}")
            if kind == "distance":
                surface = _choice(d, "tibia_surface", lw, ("convex", "concave"))
                if fr is not None and surface == "convex" and fr >= length:
                    _fail(lw, f"a convex contact needs femur_radius < length ({fr} >= {length})")
            else:
                surface = "plane"
        links.append(Link(lname, role, kind, femur, tibia, length, normal, fr, surface))
    size = max(max(float(np.abs(np.r_[lk.femur, lk.tibia]).max()), lk.length) for lk in links)
    if size < METRES_BELOW_MM:
        _fail(w, f"the links' points and lengths are all under {METRES_BELOW_MM:g} (largest {size:.3g}): they look "
                 f"like metres; parameter files are in mm")
    names = [lk.name for lk in links]
    if len(set(names)) != len(names):
        _fail(w, f"link names must be unique, got {names}")

    pf = None
    if "pf" in data:
        d = data["pf"]
        pw = f"{w} [pf]"
        if not isinstance(d, dict):
            _fail(w, f"'pf' must be a table ([pf]), got {d!r}")
        pf = PFGroup(
            axis_femur=_unit(d, "axis_femur", pw, ascale),
            point_femur=_point(d, "point_femur", pw),
            axis_patella=_unit(d, "axis_patella", pw, ascale),
            point_patella=_point(d, "point_patella", pw),
            tendon_tibia=_vector(d, "tendon_tibia", pw),
            tendon_patella=_vector(d, "tendon_patella", pw),
            tendon_length=_number(d, "tendon_length", pw),
            lambda0=_number(d, "lambda0", pw),
            lambda1=_number(d, "lambda1", pw),
            reference_flexion=math.radians(_number(d, "reference_flexion_deg", pw)),
        )
        if pf.tendon_length <= 0:
            _fail(pw, f"field 'tendon_length' must be positive, got {pf.tendon_length}")

    initial = None
    if "initial" in data:
        d = data["initial"]
        iw = f"{w} [initial]"
        if not isinstance(d, dict):
            _fail(w, f"'initial' must be a table ([initial]), got {d!r}")
        flex = math.radians(_number(d, "flexion_deg", iw))
        u = _vector(d, "tf_unknowns", iw, 5)  # beta, gamma (in the file's angle unit), x, y, z (mm)
        u[:2] *= ascale
        initial = InitialPose(flex, u)

    return MechanismParams(name=name, links=tuple(links), pf=pf, initial=initial,
                           description=str(data.get("description", "")),
                           source=str(data.get("source", "")), side=side)


def load_toml(path) -> MechanismParams:
    """Read a parameter file. Raises :class:`ModelFileError` with a one-line message."""
    p = Path(path)
    try:
        text = read_text(p, "parameter file")
    except KneeInputError as e:
        raise ModelFileError(str(e)) from None
    try:
        data = tomllib.loads(text)
    except tomllib.TOMLDecodeError as e:
        raise ModelFileError(f"{p}: not valid TOML ({e})") from None
    return params_from_dict(data, origin=str(p))


def bundled_models() -> dict[str, str]:
    """The bundled parameter sets, {name: one-line description}; each loads with :func:`load_model`."""
    out = {}
    for f in sorted(resources.files("knee.models.mechanism").joinpath("data").iterdir()):
        if f.name.endswith(".toml"):
            data = tomllib.loads(f.read_text(encoding="utf-8"))
            out[data.get("name", f.name[:-5])] = str(data.get("description", "")).strip()
    return out


def load_model(name_or_path) -> MechanismParams:
    """A bundled parameter set by name (see :func:`bundled_models`) or a TOML file by path.

    Raises
    ------
    UnknownModelError
        Neither a bundled name nor an existing file.
    ModelFileError
        The file is malformed.
    """
    s = str(name_or_path)
    res = resources.files("knee.models.mechanism").joinpath("data").joinpath(f"{s}.toml")
    if "/" not in s and not s.endswith(".toml") and res.is_file():
        data = tomllib.loads(res.read_text(encoding="utf-8"))
        return params_from_dict(data, origin=f"{s}.toml (bundled)")
    p = Path(s)
    if p.is_file():
        return load_toml(p)
    known = ", ".join(bundled_models())
    raise UnknownModelError(f"unknown model {s!r}: not a bundled set ({known}) nor an existing TOML file")


# ----------------------------------------------------------------------------------------------
# Writing


def toml_string(x: str) -> str:
    """A TOML basic string: backslash, quote and every control character escaped."""
    out = []
    for ch in x:
        if ch in ('"', "\\"):
            out.append("\\" + ch)
        elif ord(ch) < 0x20 or ord(ch) == 0x7F:
            out.append({"\n": "\\n", "\t": "\\t", "\r": "\\r"}.get(ch, f"\\u{ord(ch):04x}"))
        else:
            out.append(ch)
    return '"' + "".join(out) + '"'


def _fmt(x) -> str:
    if isinstance(x, str):
        return toml_string(x)
    if isinstance(x, (list, tuple, np.ndarray)):
        return "[" + ", ".join(_fmt(e) for e in x) + "]"
    return repr(float(x))


def dumps_toml(p: MechanismParams) -> str:
    """Serialise parameters (vectors as unit vectors, angles in radians); loads back identically."""
    lines = [f'format = "{FORMAT_NAME}"', f"version = {FORMAT_VERSION}", f"name = {_fmt(p.name)}",
             f"description = {_fmt(p.description)}", f"source = {_fmt(p.source)}",
             f"side = {_fmt(p.side)}", "", "[units]", 'length = "mm"', 'angle = "rad"', ""]
    for lk in p.links:
        lines += ["[[tf.links]]", f"name = {_fmt(lk.name)}", f"role = {_fmt(lk.role)}",
                  f"kind = {_fmt(lk.kind)}", f"femur = {_fmt(lk.femur)}", f"tibia = {_fmt(lk.tibia)}"]
        if lk.normal is not None:
            lines.append(f"normal = {_fmt(lk.normal)}")
        lines.append(f"length = {_fmt(lk.length)}")
        if lk.femur_radius is not None:
            lines.append(f"femur_radius = {_fmt(lk.femur_radius)}")
        if lk.tibia_surface in ("convex", "concave"):
            lines.append(f"tibia_surface = {_fmt(lk.tibia_surface)}")
        lines.append("")
    if p.pf is not None:
        f = p.pf
        lines += ["[pf]", f"axis_femur = {_fmt(f.axis_femur)}", f"point_femur = {_fmt(f.point_femur)}",
                  f"axis_patella = {_fmt(f.axis_patella)}", f"point_patella = {_fmt(f.point_patella)}",
                  f"tendon_tibia = {_fmt(f.tendon_tibia)}", f"tendon_patella = {_fmt(f.tendon_patella)}",
                  f"tendon_length = {_fmt(f.tendon_length)}", f"lambda0 = {_fmt(f.lambda0)}",
                  f"lambda1 = {_fmt(f.lambda1)}",
                  f"reference_flexion_deg = {_fmt(math.degrees(f.reference_flexion))}", ""]
    if p.initial is not None:
        lines += ["[initial]", f"flexion_deg = {_fmt(math.degrees(p.initial.flexion))}",
                  f"tf_unknowns = {_fmt(p.initial.unknowns)}", ""]
    return "\n".join(lines)


def save_toml(p: MechanismParams, path, overwrite: bool = False) -> Path:
    """Write ``p`` to ``path``; refuses to overwrite an existing file unless ``overwrite``."""
    path = Path(path)
    if path.exists() and not overwrite:
        raise ModelFileError(f"{path}: exists; not overwritten")
    path.write_text(dumps_toml(p), encoding="utf-8")
    return path


__all__ = ["Link", "PFGroup", "InitialPose", "MechanismParams", "load_model", "load_toml",
           "save_toml", "dumps_toml", "bundled_models", "params_from_dict", "parameter_names",
           "require_condylar_contacts", "toml_string", "N_PARAMS", "N_LINKS", "LINK_SIZE", "PF_SIZE"]
