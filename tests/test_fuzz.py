"""Every command on every class of bad input, as an adversarial user would try it.

Each case builds its inputs from generated files (nothing binary is committed), runs ``knee ...`` in this
process and asserts what the README promises: the documented exit code, one line ``knee: error: ...`` on
standard error naming the file, field or flag, no traceback, and no existing file changed (every file
under the case's folder is hashed before and after). A run that hangs fails through an alarm.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import os
import re
import shutil
import signal
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from knee.app.cli import main
from knee.fitting.synthetic import make_subject
from knee.foundations.imaging import read_markups, write_markups
from knee.models.mechanism.params import dumps_toml, load_model

TIMEOUT_S = 90


@dataclass
class Outcome:
    code: int
    stdout: str
    stderr: str


def _alarm(signum, frame):
    raise TimeoutError("the command did not finish in time")


def knee(*args) -> Outcome:
    out, err = io.StringIO(), io.StringIO()
    old = signal.signal(signal.SIGALRM, _alarm)
    signal.alarm(TIMEOUT_S)
    try:
        with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
            try:
                code = main([str(a) for a in args])
            except SystemExit as e:
                code = e.code if isinstance(e.code, int) else 1
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, old)
    return Outcome(code, out.getvalue(), err.getvalue())


def snapshot(root: Path) -> dict[str, str]:
    """Hash of every file under ``root`` (and the list of folders), to prove nothing was changed."""
    h = {}
    for p in sorted(root.rglob("*")):
        rel = str(p.relative_to(root))
        h[rel] = hashlib.sha256(p.read_bytes()).hexdigest() if p.is_file() else "dir"
    return h


# ----------------------------------------------------------------------------------------------
# Inputs


@pytest.fixture(scope="module")
def base(tmp_path_factory):
    """Good inputs every case starts from: a parameter file, a subject folder, a gait trial, depth files."""
    root = tmp_path_factory.mktemp("fuzz-base")
    vol = load_model("volunteer")
    (root / "good.toml").write_text(dumps_toml(vol), encoding="utf-8")
    make_subject(root / "subject", seed=0, frames=12)
    return root


@pytest.fixture
def case(base, tmp_path):
    """A fresh copy of the good inputs for one case, in ``tmp_path``."""
    shutil.copy(base / "good.toml", tmp_path / "good.toml")
    shutil.copytree(base / "subject", tmp_path / "subject")
    (tmp_path / "a-file.txt").write_text("not a folder\n")
    (tmp_path / "a-folder").mkdir()
    return tmp_path


def toml_text(case: Path) -> str:
    return (case / "good.toml").read_text()


def write(case: Path, name: str, content) -> Path:
    p = case / name
    p.parent.mkdir(parents=True, exist_ok=True)
    if isinstance(content, bytes):
        p.write_bytes(content)
    else:
        p.write_text(content)
    return p


def links_block_replaced(case: Path, new: str) -> str:
    """The good parameter file with its [[tf.links]] array replaced by ``new``."""
    text = toml_text(case)
    head = text.split("[[tf.links]]")[0]
    tail = "[pf]" + text.split("[pf]", 1)[1]
    return head + new + "\n" + tail


def one_contact(case: Path) -> Path:
    """A valid parameter file whose lateral contact is declared a ligament: one contact link, not two."""
    text = toml_text(case)
    blocks = text.split("[[tf.links]]")
    for i, b in enumerate(blocks):
        if 'name = "lc"' in b:
            blocks[i] = b.replace('role = "contact"', 'role = "ligament"').replace(
                'tibia_surface = "concave"\n', "").replace('tibia_surface = "convex"\n', "")
    return write(case, "one-contact.toml", "[[tf.links]]".join(blocks))


def latin1(text: str) -> bytes:
    return ("# commentaire: g\u00e9n\u00e9r\u00e9\n" + text).encode("latin-1")


def subject_with(case: Path, rel: str, content) -> Path:
    write(case, f"subject/{rel}", content)
    return case / "subject"


def markups_doc(markups) -> str:
    return json.dumps({"markups": markups})


def npy_bytes(array) -> bytes:
    buf = io.BytesIO()
    np.save(buf, array, allow_pickle=True)
    return buf.getvalue()


# Each case: (id, builder(case) -> argv list, exit code, fragment the error line must contain).
INTR = "300,300,80,60"
CASES = [
    # ---- output paths
    ("sweep-out-folder", lambda c: ["sweep", "volunteer", "--out", c / "a-folder"], 2, "a-folder"),
    ("sweep-out-under-file", lambda c: ["sweep", "volunteer", "--out", c / "a-file.txt/x.csv"], 2, "a-file.txt"),
    ("sweep-out-proc", lambda c: ["sweep", "volunteer", "--out", "/proc/x.csv"], 2, "/proc"),
    ("sweep-out-dev-full", lambda c: ["sweep", "volunteer", "--out", "/dev/full", "--force"], 2, "/dev/full"),
    ("sweep-rrd-folder", lambda c: ["sweep", "volunteer", "--rrd", c / "a-folder", "--force"], 2, "a-folder"),
    ("sweep-out-is-input", lambda c: ["sweep", c / "good.toml", "--out", c / "good.toml", "--force"], 2,
     "good.toml"),
    ("sweep-out-is-rrd", lambda c: ["sweep", "volunteer", "--out", c / "x", "--rrd", c / "x", "--force"], 2, "x"),
    ("demo-out-under-file", lambda c: ["demo", "--out", c / "a-file.txt/d", "--kinematics-only"], 2, "a-file.txt"),
    ("demo-out-proc", lambda c: ["demo", "--out", "/proc/knee-demo", "--kinematics-only"], 2, "/proc"),
    ("synth-under-file", lambda c: ["synth-subject", c / "a-file.txt/s"], 2, "a-file.txt"),
    ("synth-proc", lambda c: ["synth-subject", "/proc/s"], 2, "/proc"),
    ("synth-is-file", lambda c: ["synth-subject", c / "a-file.txt"], 2, "a-file.txt"),
    ("fit-out-proc", lambda c: ["fit", c / "subject", "--out", "/proc/fit", "--quick"], 2, "/proc"),
    ("fit-out-under-file", lambda c: ["fit", c / "subject", "--out", c / "a-file.txt/o", "--quick"], 2,
     "a-file.txt"),
    ("fit-out-file", lambda c: ["fit", c / "subject", "--out", c / "a-file.txt", "--quick", "--force"], 2,
     "a-file.txt"),
    ("fit-out-is-subject", lambda c: ["fit", c / "subject", "--out", c / "subject", "--force"], 2, "subject"),
    ("gait-out-proc", lambda c: ["gait", "volunteer", "--out", "/proc/g"], 2, "/proc"),
    ("gait-trial-in-out", lambda c: ["gait", "volunteer", "--trial", write(c, "g/gait.csv", "time_s\n"),
                                     "--out", c / "g", "--force"], 2, "gait.csv"),
    ("gait-rrd-is-trial", lambda c: ["gait", "volunteer", "--trial", write(c, "gait.csv", "time_s\n"),
                                     "--rrd", c / "gait.csv", "--out", c / "o", "--force"], 2, "gait.csv"),
    ("contact-out-file", lambda c: ["contact", "volunteer", "--out", c / "a-file.txt", "--force"], 2, "a-file.txt"),
    ("osteotomy-out-proc", lambda c: ["osteotomy", "volunteer", "--angle", 5, "--out", "/proc/o"], 2, "/proc"),
    ("compare-out-under-file", lambda c: ["compare", "volunteer", "--out", c / "a-file.txt/o", "--flexion", 60,
                                          "--methods", "kinematics"], 2, "a-file.txt"),
    ("fem-rrd-proc", lambda c: ["fem", "volunteer", "--rrd", "/proc/x.rrd"], 2, "/proc"),
    # ---- text files that are not UTF-8
    ("sweep-toml-latin1", lambda c: ["sweep", write(c, "l1.toml", latin1(toml_text(c)))], 2, "l1.toml"),
    ("fit-motion-latin1", lambda c: ["fit", subject_with(c, "motion.csv", latin1(
        (c / "subject/motion.csv").read_text())), "--out", c / "o", "--quick"], 2, "motion.csv"),
    ("fit-subject-toml-latin1", lambda c: ["fit", subject_with(c, "subject.toml", latin1(
        (c / "subject/subject.toml").read_text())), "--out", c / "o", "--quick"], 2, "subject.toml"),
    ("gait-csv-latin1", lambda c: ["gait", "volunteer", "--trial", write(c, "g.csv", b"time_s,h\xe9\n1,2\n"),
                                   "--out", c / "o"], 2, "g.csv"),
    ("gait-trial-folder", lambda c: ["gait", "volunteer", "--trial", c / "a-folder", "--out", c / "o"], 2,
     "a-folder"),
    ("sweep-toml-folder", lambda c: ["sweep", c / "a-folder"], 2, "a-folder"),
    # ---- wrongly typed parameter files
    ("toml-links-numbers", lambda c: ["sweep", write(c, "t.toml", links_block_replaced(
        c, "[tf]\nlinks = [1, 2, 3, 4, 5]\n"))], 2, "tf.links"),
    ("toml-pf-number", lambda c: ["sweep", write(c, "t.toml", toml_text(c).split("[pf]")[0].replace(
        'side = "right"', 'side = "right"\npf = 3'))], 2, "pf"),
    ("toml-name-number", lambda c: ["sweep", write(c, "t.toml", toml_text(c).replace(
        'name = "volunteer"', "name = 5", 1))], 2, "name"),
    ("toml-units-number", lambda c: ["sweep", write(c, "t.toml", toml_text(c).replace(
        '[units]\nlength = "mm"\nangle = "rad"', "").replace('side = "right"', 'side = "right"\nunits = 3'))],
     2, "units"),
    ("toml-initial-string", lambda c: ["sweep", write(c, "t.toml", toml_text(c).split("[initial]")[0].replace(
        'side = "right"', 'side = "right"\ninitial = "x"'))], 2, "initial"),
    ("toml-tf-list", lambda c: ["sweep", write(c, "t.toml", links_block_replaced(c, "").replace(
        'side = "right"', 'side = "right"\ntf = [1]'))], 2, "tf"),
    ("toml-metres", lambda c: ["sweep", write(c, "m.toml", _in_metres(toml_text(c)))], 2, "metres"),
    # ---- other than two contact links
    ("sweep-rrd-one-contact", lambda c: ["sweep", one_contact(c), "--rrd", c / "s.rrd"], 2, "contact"),
    ("fem-one-contact", lambda c: ["fem", one_contact(c), "--flexion", 60], 2, "contact"),
    ("osteotomy-one-contact", lambda c: ["osteotomy", one_contact(c), "--angle", 5, "--out", c / "o"], 2,
     "contact"),
    ("contact-one-contact", lambda c: ["contact", one_contact(c), "--out", c / "o"], 2, "contact"),
    ("gait-one-contact", lambda c: ["gait", one_contact(c), "--out", c / "o"], 2, "contact"),
    ("compare-one-contact", lambda c: ["compare", one_contact(c), "--flexion", 60, "--out", c / "o"], 2,
     "contact"),
    # ---- subject folders
    ("subject-bundles-string", lambda c: ["fit", subject_with(c, "subject.toml", (
        c / "subject/subject.toml").read_text() + '\nbundles = "am"\n'), "--out", c / "o", "--quick"], 2,
     "bundles"),
    ("subject-pf-number", lambda c: ["fit", subject_with(c, "subject.toml", (c / "subject/subject.toml")
                                                         .read_text().split("[pf]")[0] + "pf = 3\n"),
                                     "--out", c / "o", "--quick"], 2, "pf"),
    ("subject-project-tendon-string", lambda c: ["fit", subject_with(c, "subject.toml", _subject_pf(
        c, 'project_tendon = "no"')), "--out", c / "o", "--quick"], 2, "project_tendon"),
    ("subject-name-number", lambda c: ["fit", subject_with(c, "subject.toml", _subject_toml_with(
        c, "name = 5", drop="name")), "--out", c / "o", "--quick"], 2, "name"),
    ("markups-numbers", lambda c: ["fit", subject_with(c, "ct/landmarks.mrk.json", markups_doc([1, 2])),
                                   "--out", c / "o", "--quick"], 2, "landmarks.mrk.json"),
    ("markups-string-positions", lambda c: ["fit", subject_with(c, "ct/landmarks.mrk.json", markups_doc(
        [{"controlPoints": [{"label": "x", "position": "1,2,3"}]}])), "--out", c / "o", "--quick"], 2,
     "landmarks.mrk.json"),
    ("markups-controlpoints-number", lambda c: ["fit", subject_with(c, "ct/landmarks.mrk.json", markups_doc(
        [{"controlPoints": 7}])), "--out", c / "o", "--quick"], 2, "landmarks.mrk.json"),
    ("markups-not-list", lambda c: ["fit", subject_with(c, "ct/landmarks.mrk.json", json.dumps(
        {"markups": {"a": 1}})), "--out", c / "o", "--quick"], 2, "landmarks.mrk.json"),
    ("labels-string-indices", lambda c: ["fit", _labels(c, ["a", "b", "c", "d"]), "--out", c / "o", "--quick"],
     2, "femur.json"),
    ("labels-float-indices", lambda c: ["fit", _labels(c, [0.5, 1.5, 2.5, 3.7]), "--out", c / "o", "--quick"],
     2, "femur.json"),
    ("labels-list-document", lambda c: ["fit", _labels(c, None, doc="[1, 2]"), "--out", c / "o", "--quick"],
     2, "femur.json"),
    ("landmarks-metres", lambda c: ["fit", _scaled_landmarks(c, 1e-3), "--out", c / "o", "--quick"], 2,
     "metres"),
    ("landmarks-wrong-space", lambda c: ["fit", _landmarks_flipped(c), "--out", c / "o", "--quick"], 2,
     "landmarks.mrk.json"),
    ("surface-space-wrong", lambda c: ["fit", _surface_space_lie(c), "--out", c / "o", "--quick"], 2,
     "femur"),
    ("motion-header-only", lambda c: ["fit", subject_with(c, "motion.csv", (c / "subject/motion.csv")
                                                          .read_text().splitlines()[0] + "\n"), "--out", c / "o",
                                      "--quick"], 2, "motion.csv"),
    ("motion-value-huge", lambda c: ["fit", _motion_value(c, "1e308"), "--out", c / "o", "--quick"], 2,
     "motion.csv: tf_flexion_deg is 1e+308 in data row 3"),
    ("motion-timestamps-as-translation", lambda c: ["fit", _motion_value(c, "1701234567", col=5), "--out", c / "o",
                                                    "--quick"], 2, "tf_proximal_mm is 1.70123e+09"),
    ("landmark-given-twice", lambda c: ["fit", _landmark_twice(c), "--out", c / "o", "--quick"], 2,
     "given 2 times at different positions"),
    ("motion-folder", lambda c: ["fit", _replace_with_folder(c, "subject/motion.csv"), "--out", c / "o",
                                 "--quick"], 2, "motion.csv"),
    # ---- depth files and clouds
    ("depth-object-npy", lambda c: _fem_depth(c, npy_bytes(np.array([{"a": 1}], dtype=object))), 2, "d.npy"),
    ("depth-string-npy", lambda c: _fem_depth(c, npy_bytes(np.array([["a", "b"], ["c", "d"]])), "d.npy"), 2,
     "d.npy"),
    ("depth-truncated-npy", lambda c: _fem_depth(c, npy_bytes(np.ones((120, 160)))[:300]), 2, "d.npy"),
    ("depth-png-not-image", lambda c: _fem_depth(c, b"\x89PNG\r\n\x1a\nnot really", "d.png"), 2, "d.png"),
    ("depth-1d-npy", lambda c: _fem_depth(c, npy_bytes(np.ones(10))), 2, "d.npy"),
    ("depth-wrong-size", lambda c: _fem_depth(c, npy_bytes(np.full((50, 50), 400.0))), 2, "intrinsics"),
    ("cloud-garbage", lambda c: ["fem", "volunteer", "--cloud", write(c, "c.ply", b"ply\ngarbage\x00\x01")], 2,
     "c.ply"),
    ("cloud-empty-xyz", lambda c: ["fem", "volunteer", "--cloud", write(c, "c.xyz", "")], 2, "c.xyz"),
    ("cloud-truncated-ply", lambda c: _fem_cloud(c, "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\n"
                                                    "property float y\nproperty float z\nend_header\n1 2 400\n3"),
     2, "c.ply: truncated"),
    ("fem-initial-pose-scaled", lambda c: _fem_depth(c, npy_bytes(np.full((120, 160), 400.0)), extra=(
        "--initial-pose", write(c, "p.txt", "2 0 0 0\n0 2 0 0\n0 0 2 0\n0 0 0 1\n"))), 2, "p.txt: its upper-left"),
    ("fem-initial-pose-transposed", lambda c: _fem_depth(c, npy_bytes(np.full((120, 160), 400.0)), extra=(
        "--initial-pose", write(c, "p.txt", "1 0 0 0\n0 1 0 0\n0 0 1 0\n10 20 30 1\n"))), 2, "p.txt: its last row"),
    ("fem-pose-short", lambda c: ["fem", "volunteer", "--cloud", write(c, "c.xyz", "1 2 3\n"), "--pose",
                                  write(c, "p.txt", "1 0 0\n")], 2, "--pose"),
    ("fem-pose-reflection", lambda c: ["fem", "volunteer", "--cloud", write(c, "c.xyz", "1 2 3\n"), "--pose",
                                       write(c, "p.txt", "-1 0 0 0\n0 1 0 0\n0 0 1 0\n0 0 0 1\n")], 2, "not a rotation"),
    ("subject-skin-inside-bones", lambda c: _fem_cloud(_skin_shrunk(c), "0 0 400\n100 100 500\n", "c.xyz"), 2,
     "/subject: "),
    ("subject-skin-truncated", lambda c: ["fit", _cut_short(c, "subject/ct/skin.stl"), "--out", c / "o", "--quick"],
     2, "skin.stl: truncated"),
    ("subject-femur-truncated", lambda c: ["fit", _cut_short(c, "subject/ct/femur.stl"), "--out", c / "o",
                                           "--quick"], 2, "femur.stl: truncated"),
    # ---- numbers and sizes
    ("seed-negative-fit", lambda c: ["fit", c / "subject", "--out", c / "o", "--seed", -1], 2, "--seed"),
    ("seed-negative-synth", lambda c: ["synth-subject", c / "s", "--seed", -1], 2, "--seed"),
    ("compare-flexion-inf", lambda c: ["compare", "volunteer", "--flexion", "30:40:inf", "--out", c / "o"], 2,
     "--flexion"),
    ("compare-flexion-nan", lambda c: ["compare", "volunteer", "--flexion", "nan", "--out", c / "o"], 2,
     "--flexion"),
    ("synth-frames-huge", lambda c: ["synth-subject", c / "s", "--frames", 10_000_000], 2, "--frames"),
    ("synth-frames-zero", lambda c: ["synth-subject", c / "s", "--frames", 0], 2, "--frames"),
    ("compare-frames-huge", lambda c: ["compare", c / "subject", "--prior", c / "subject/truth.toml",
                                       "--truth-motion", c / "subject/motion.csv", "--frames", 10_000_000,
                                       "--out", c / "o"], 2, "--frames"),
    ("fem-max-steps-huge", lambda c: ["fem", "volunteer", "--max-steps", 10 ** 9], 2, "--max-steps"),
    ("fem-max-steps-zero", lambda c: ["fem", "volunteer", "--max-steps", 0], 2, "--max-steps"),
    ("gait-mass-nan", lambda c: ["gait", "volunteer", "--mass", "nan", "--out", c / "o"], 2, "mass"),
    ("gait-height-inf", lambda c: ["gait", "volunteer", "--height", "inf", "--out", c / "o"], 2, "height"),
    ("contact-load-negative", lambda c: ["contact", "volunteer", "--load", -5, "--out", c / "o"], 2, "--load"),
    ("osteotomy-angle-nan", lambda c: ["osteotomy", "volunteer", "--angle", "nan", "--out", c / "o"], 2,
     "--angle"),
    ("demo-flexion-nan", lambda c: ["demo", "--flexion", "nan", "--out", c / "d"], 2, "--flexion"),
    ("fem-depth-scale-zero", lambda c: _fem_depth(c, npy_bytes(np.full((120, 160), 400.0)), extra=(
        "--depth-scale", 0)), 2, "--depth-scale"),
    # ---- gait files with wrong units or gaps
    ("gait-time-ms", lambda c: ["gait", "volunteer", "--trial", _gait_ms(c), "--out", c / "o"], 2, "time_s"),
    ("gait-grf-gaps", lambda c: ["gait", "volunteer", "--trial", _gait_gaps(c), "--out", c / "o"], 2, "grf"),
]


def _in_metres(text: str) -> str:
    """The parameter file with every length (points, lengths, radii, pitch) divided by 1000."""
    out = []
    for line in text.splitlines():
        key = line.split("=")[0].strip()
        if key in ("femur", "tibia", "length", "femur_radius", "point_femur", "point_patella", "tendon_tibia",
                   "tendon_patella", "tendon_length", "lambda0", "lambda1"):
            nums = line.split("=", 1)[1]
            scaled = re.sub(r"-?\d+\.\d*(e-?\d+)?", lambda m: repr(float(m.group(0)) * 1e-3), nums)
            line = f"{key} = {scaled.strip()}"
        out.append(line)
    return "\n".join(out) + "\n"


def _subject_toml_with(c: Path, line: str, drop: str | None = None) -> str:
    lines = (c / "subject/subject.toml").read_text().splitlines()
    if drop:
        lines = [ln for ln in lines if not ln.startswith(drop + " ")]
    first_table = next((i for i, ln in enumerate(lines) if ln.startswith("[")), len(lines))
    lines.insert(first_table, line)
    return "\n".join(lines) + "\n"


def _subject_pf(c: Path, line: str) -> str:
    text = (c / "subject/subject.toml").read_text()
    assert "project_tendon = false" in text
    return text.replace("project_tendon = false", line)


def _labels(c: Path, idx, doc: str | None = None) -> Path:
    (c / "subject/mri/areas/femur_lateral_condyle.mrk.json").unlink()
    write(c, "subject/mri/labels/femur.json", doc if doc is not None else json.dumps({"femur_lateral_condyle": idx}))
    return c / "subject"


def _scaled_landmarks(c: Path, s: float) -> Path:
    f = c / "subject/ct/landmarks.mrk.json"
    mk = read_markups(f)
    write_markups(f, mk.labels, mk.points * s)
    return c / "subject"


def _landmarks_flipped(c: Path) -> Path:
    """Landmarks whose file says LPS while its numbers are RAS (x and y negated)."""
    f = c / "subject/ct/landmarks.mrk.json"
    mk = read_markups(f)
    write_markups(f, mk.labels, mk.points * np.array([-1.0, -1.0, 1.0]))
    return c / "subject"


def _surface_space_lie(c: Path) -> Path:
    """The CT femur's STL header says RAS while its numbers are LPS."""
    f = c / "subject/ct/femur.stl"
    data = bytearray(f.read_bytes())
    data[:80] = b"SPACE=RAS".ljust(80, b" ")
    f.write_bytes(bytes(data))
    return c / "subject"


def _motion_value(c: Path, value: str, col: int = 1, row: int = 3) -> Path:
    """The subject's motion.csv with one value replaced (column ``col`` of data row ``row``, 1-based)."""
    f = c / "subject/motion.csv"
    lines = f.read_text().splitlines()
    cells = lines[row].split(",")
    cells[col] = value
    lines[row] = ",".join(cells)
    f.write_text("\n".join(lines) + "\n")
    return c / "subject"


def _landmark_twice(c: Path) -> Path:
    """The CT landmarks with their first point given a second time, elsewhere."""
    f = c / "subject/ct/landmarks.mrk.json"
    mk = read_markups(f)
    write_markups(f, list(mk.labels) + [mk.labels[0]], np.vstack([mk.points, mk.points[0] + 20.0]))
    return c / "subject"


def _replace_with_folder(c: Path, rel: str) -> Path:
    (c / rel).unlink()
    (c / rel).mkdir()
    return c / "subject"


def _fem_depth(c: Path, content: bytes, name: str = "d.npy", extra=()) -> list:
    return ["fem", c / "subject", "--prior", c / "subject/truth.toml", "--depth", write(c, name, content),
            "--intrinsics", INTR, "--out", c / "o", *extra]


def _fem_cloud(c: Path, content: str, name: str = "c.ply") -> list:
    return ["fem", c / "subject", "--prior", c / "subject/truth.toml", "--cloud", write(c, name, content),
            "--out", c / "o"]


def _skin_shrunk(c: Path) -> Path:
    """The subject's skin shrunk to half its size about its centre: the bones stick out of it."""
    from knee.foundations.imaging import read_surface, write_surface

    f = c / "subject/ct/skin.stl"
    skin = read_surface(f)
    centre = skin.vertices.mean(axis=0)
    skin.vertices = (skin.vertices - centre) * 0.5 + centre
    write_surface(f, skin)
    return c


def _cut_short(c: Path, rel: str) -> Path:
    """A subject's binary STL cut after half its bytes (an interrupted copy)."""
    f = c / rel
    data = f.read_bytes()
    f.write_bytes(data[:len(data) // 2 + 7])
    return c / "subject"


def _gait_ms(c: Path) -> Path:
    from knee.models.gait import normative_trial

    tr = normative_trial(72.0)
    rows = ["time_s,hip_flexion_deg,knee_flexion_deg,ankle_dorsiflexion_deg,grf_anterior_N,grf_vertical_N"]
    for k in range(len(tr.time)):
        rows.append(f"{tr.time[k] * 1000:.3f},{np.degrees(tr.hip[k, 0]):.3f},{np.degrees(tr.knee[k]):.3f},"
                    f"{np.degrees(tr.ankle[k]):.3f},{tr.grf[k, 0]:.3f},{tr.grf[k, 1]:.3f}")
    return write(c, "gait-ms.csv", "\n".join(rows) + "\n")


def _gait_gaps(c: Path) -> Path:
    from knee.models.gait import normative_trial

    tr = normative_trial(72.0)
    rows = ["time_s,hip_flexion_deg,knee_flexion_deg,ankle_dorsiflexion_deg,grf_anterior_N,grf_vertical_N"]
    for k in range(len(tr.time)):
        v = "" if 5 <= k < 15 else f"{tr.grf[k, 1]:.3f}"
        rows.append(f"{tr.time[k]:.4f},{np.degrees(tr.hip[k, 0]):.3f},{np.degrees(tr.knee[k]):.3f},"
                    f"{np.degrees(tr.ankle[k]):.3f},{tr.grf[k, 0]:.3f},{v}")
    return write(c, "gait-gaps.csv", "\n".join(rows) + "\n")


@pytest.mark.parametrize("name,build,code,fragment", CASES, ids=[c[0] for c in CASES])
def test_bad_input_is_one_line_and_changes_nothing(case, name, build, code, fragment, monkeypatch):
    argv = build(case)
    before = snapshot(case)
    monkeypatch.chdir(case)  # a command that writes a default output folder writes it here
    r = knee(*argv)
    assert "Traceback" not in r.stderr, r.stderr
    assert r.code == code, f"exit {r.code}, expected {code}: {r.stderr[-2000:]}"
    after = snapshot(case)
    changed = [k for k in before if after.get(k) != before[k]]
    assert not changed, f"changed or removed: {changed}"
    if code == 0:
        return
    errors = [ln for ln in r.stderr.splitlines() if "error" in ln.lower()]
    assert len(errors) == 1, r.stderr
    assert errors[0].startswith("knee: error: ") or errors[0].startswith("usage:") or "error:" in errors[0]
    assert fragment in errors[0], errors[0]
    new = [k for k in after if k not in before]
    results = [k for k in new if not k.startswith(".")]
    assert not results, f"a failed run left {results}"


# ----------------------------------------------------------------------------------------------
# Nothing lost, nothing misleading


def test_force_replaces_the_whole_output_set_and_an_interrupted_run_keeps_the_previous(tmp_path, monkeypatch):
    out = tmp_path / "c"
    assert knee("contact", "volunteer", "--out", out).code == 0
    (out / "stale.txt").write_text("from an older run\n")
    assert knee("contact", "volunteer", "--out", out, "--force").code == 0
    assert sorted(f.name for f in out.iterdir()) == ["contact.csv", "contact.png"]  # stale.txt went with the set
    before = snapshot(tmp_path)

    def interrupted(*a, **k):
        raise KeyboardInterrupt

    monkeypatch.setattr("knee.app.commands.contact.plot_contact", interrupted)
    r = knee("contact", "volunteer", "--out", out, "--force")
    assert r.code == 130 and r.stderr.strip().splitlines()[-1].startswith("knee: error: interrupted")
    assert snapshot(tmp_path) == before  # the previous results, whole; no partial folder beside them

    def disk_full(res, path, *a, **k):
        raise OSError(28, "No space left on device", str(path))

    monkeypatch.setattr("knee.app.commands.contact.plot_contact", disk_full)
    r = knee("contact", "volunteer", "--out", out, "--force")
    assert r.code == 2 and "Traceback" not in r.stderr
    assert r.stderr.strip().splitlines()[-1].endswith("contact.png: No space left on device; no results written")
    assert snapshot(tmp_path) == before


def test_a_failure_while_writing_leaves_no_partial_file(tmp_path, monkeypatch):
    from knee.foundations.files import staged_file, staged_folder

    f = tmp_path / "table.csv"
    f.write_text("previous\n")
    with pytest.raises(OSError):
        with staged_file(f) as tmp:
            tmp.write_text("half")
            raise OSError(28, "No space left on device")
    assert f.read_text() == "previous\n" and sorted(p.name for p in tmp_path.iterdir()) == ["table.csv"]
    d = tmp_path / "results"
    with pytest.raises(RuntimeError):
        with staged_folder(d) as tmp:
            (tmp / "a.csv").write_text("x")
            raise RuntimeError("diverged")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["table.csv"]


def test_records_written_whole_with_their_first_keys_as_columns(tmp_path):
    """The scripts' tables: every record under the first one's keys, read back as written; none, no file; a
    record with a key the first lacks fails before the table replaces the one there."""
    import csv

    from knee.foundations.files import write_records

    f = tmp_path / "rows.csv"
    write_records(f, ({"case": f"c{i}", "mm": 0.5 * i} for i in range(3)))
    assert list(csv.DictReader(f.open())) == [{"case": f"c{i}", "mm": str(0.5 * i)} for i in range(3)]
    write_records(tmp_path / "none.csv", [])
    assert not (tmp_path / "none.csv").exists()
    with pytest.raises(ValueError):
        write_records(f, [{"case": "a"}, {"case": "b", "extra": 1}])
    assert f.read_text().splitlines()[0] == "case,mm" and sorted(p.name for p in tmp_path.iterdir()) == ["rows.csv"]


def test_every_parameter_file_the_toolkit_writes_loads_back(tmp_path):
    from dataclasses import replace

    from knee.models.mechanism.params import save_toml

    vol = load_model("volunteer")
    odd = replace(vol, name='knee "A"\nsecond line\tand \\ a tab \x07', description="line 1\nline 2\r\n",
                  source="é ü 膝")
    back = load_model(save_toml(odd, tmp_path / "odd.toml"))
    assert (back.name, back.description, back.source) == (odd.name, odd.description, odd.source)
    np.testing.assert_array_equal(back.to_vector(), vol.to_vector())


def _interrupt_when(marker: str, *args, sig=signal.SIGINT) -> tuple[int, str, float]:
    """``knee ARGS`` in a child process, Ctrl-C (or ``sig``) as soon as ``marker`` appears on its standard
    error (the work under way): (exit code, stderr, seconds from the signal to its end)."""
    import select
    import subprocess
    import sys
    import time

    p = subprocess.Popen([sys.executable, "-m", "knee.app.cli", *map(str, args)], stdout=subprocess.DEVNULL,
                         stderr=subprocess.PIPE, preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    err, deadline = b"", time.monotonic() + 120
    while marker.encode() not in err and time.monotonic() < deadline and p.poll() is None:
        if select.select([p.stderr], [], [], 0.1)[0]:
            err += os.read(p.stderr.fileno(), 4096)
    assert p.poll() is None, f"finished before the interrupt: {err.decode()}"
    t0 = time.monotonic()
    p.send_signal(sig)
    _, rest = p.communicate(timeout=120)
    return p.returncode, (err + rest).decode(), time.monotonic() - t0


@pytest.mark.parametrize("command", ["demo", "fit"])
def test_ctrl_c_stops_at_once_with_one_line_and_no_results(tmp_path, base, command):
    out = tmp_path / "out"
    if command == "demo":  # interrupted while the FEM workers run
        code, err, stop = _interrupt_when("sweeping the bundled", "demo", "--out", out)
    else:  # interrupted in the fit's global stage
        code, err, stop = _interrupt_when("generation 2", "fit", base / "subject", "--out", out)
    assert code == 130, err
    assert "Traceback" not in err and err.strip().splitlines()[-1] == "knee: error: interrupted; no results written"
    assert not out.exists() and not [p for p in tmp_path.iterdir()]  # nothing, not even a hidden partial folder
    # the demo's FEM workers are stopped, not waited for: none of them reports its case done (before, the
    # demo waited about 20 s for them and wrote results); the time to stop is in scripts/bench_interrupt.py
    assert " done after " not in err, err


def test_a_termination_request_is_taken_as_ctrl_c(tmp_path):
    """SIGTERM (``kill``, a scheduler's time limit) to ``knee demo`` while its FEM workers run: the same
    one line and exit code as Ctrl-C, the workers stopped, nothing written, not even a hidden partial
    folder (before, the process died where it stood and left its partial output)."""
    out = tmp_path / "out"
    code, err, _ = _interrupt_when("sweeping the bundled", "demo", "--out", out, sig=signal.SIGTERM)
    assert code == 130, err
    assert "Traceback" not in err and err.strip().splitlines()[-1] == "knee: error: interrupted; no results written"
    assert not out.exists() and not [p for p in tmp_path.iterdir()]
    assert " done after " not in err, err


BOUND_CASES = [
    ("fit-bounds-unknown", lambda c: ["fit", c / "subject", "--out", c / "o", "--bounds", "tf_radius=3"], 2,
     "tf_radius"),
    ("fit-bounds-negative", lambda c: ["fit", c / "subject", "--out", c / "o", "--bounds", "pf_axis_deg=-1"], 2,
     "pf_axis_deg"),
    ("fit-assemble-over-bad", lambda c: ["fit", c / "subject", "--out", c / "o", "--assemble-over", "120:0"], 2,
     "--assemble-over"),
    ("fit-noise-unknown", lambda c: ["fit", c / "subject", "--out", c / "o", "--noise", "flexion=2"], 2,
     "flexion"),
    ("fit-noise-zero", lambda c: ["fit", c / "subject", "--out", c / "o", "--noise", "sagittal_mm=0"], 2,
     "sagittal_mm"),
    ("fit-check-trial-missing", lambda c: ["fit", c / "subject", "--out", c / "o", "--check-trial",
                                           c / "nope.csv"], 2, "nope.csv"),
    ("fit-also-trial-in-out", lambda c: ["fit", c / "subject", "--out", c / "a-folder", "--force", "--also-trial",
                                         write(c, "a-folder/t.csv", "x\n")], 2, "t.csv"),
    ("fit-check-trial-latin1", lambda c: ["fit", c / "subject", "--out", c / "o", "--check-trial",
                                          write(c, "t.csv", latin1("tf_flexion_deg\n"))], 2, "t.csv"),
    ("fit-bounds-not-pairs", lambda c: ["fit", c / "subject", "--out", c / "o", "--bounds", "4"], 2, "--bounds"),
    ("subject-fit-bounds-string", lambda c: ["fit", subject_with(c, "subject.toml", (c / "subject/subject.toml")
                                                                 .read_text() + '\n[fit]\ntf_endpoint_mm = "4"\n'),
                                             "--out", c / "o"], 2, "tf_endpoint_mm"),
    ("subject-fit-bounds-huge", lambda c: ["fit", subject_with(c, "subject.toml", (c / "subject/subject.toml")
                                                               .read_text() + "\n[fit]\npf_axis_deg = 400\n"),
                                           "--out", c / "o"], 2, "pf_axis_deg"),
]


@pytest.mark.parametrize("name,build,code,fragment", BOUND_CASES, ids=[c[0] for c in BOUND_CASES])
def test_bad_fit_bounds_are_refused_before_the_fit(case, name, build, code, fragment, monkeypatch):
    test_bad_input_is_one_line_and_changes_nothing(case, name, build, code, fragment, monkeypatch)
