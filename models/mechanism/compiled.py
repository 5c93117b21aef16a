"""Code generation, compilation and loading of the mechanism's CasADi functions.

The functions of :mod:`knee.models.mechanism.closure` (one continuation step, a chunked sweep, a TF Newton
solve) depend only on the *structure* of the mechanism: the kinds of its five links and whether it has
a patella. For each structure the C code is generated once, compiled with the system C compiler
(``$CC`` or ``cc``/``gcc``) into a shared library, and cached on disk under
``$KNEE_CACHE_DIR`` (default ``~/.cache/knee-toolkit``), keyed by a hash of the generated source and the
compiler flags. A cached library is loaded only from a folder that belongs to the user and that no one
else can write to, and only when it matches the SHA-256 recorded beside it when it was compiled;
otherwise it is compiled again (into a private temporary folder when the cache folder is not safe). The library is called through ``ctypes`` with preallocated buffers, which keeps the
per-call overhead to a microsecond or two.

When no C compiler is found, or compiling fails, the same functions run through CasADi's own virtual
machine (:class:`CasadiBackend`), slower but identical in results. ``KNEE_NO_COMPILE=1`` forces that
fallback.

Threads: the generated functions and the loaded library are shared by the whole process (built once
under a lock), but the buffers they are called with belong to one thread: :func:`backend` gives each
thread its own :class:`Backend`, so two mechanisms of one structure can be solved from two threads.
"""

from __future__ import annotations

import atexit
import ctypes
import hashlib
import logging
import os
import shutil
import subprocess
import tempfile
import threading
from pathlib import Path

import casadi as ca
import numpy as np

from knee.models.mechanism import closure

log = logging.getLogger(__name__)

GENERATOR_VERSION = "4"
CFLAGS = ["-O3", "-fPIC", "-shared"]


def cache_dir() -> Path:
    d = os.environ.get("KNEE_CACHE_DIR")
    return Path(d) if d else Path.home() / ".cache" / "knee-toolkit"


def find_compiler() -> str | None:
    """The C compiler to use, or None."""
    cc = os.environ.get("CC")
    if cc and shutil.which(cc):
        return cc
    for c in ("cc", "gcc", "clang"):
        if shutil.which(c):
            return c
    return None


def build_functions(kinds, has_pf) -> dict[str, ca.Function]:
    step = closure.build_step(kinds, has_pf)
    newton = closure.build_tf_newton(kinds)
    return {"knee_step": step, "knee_sweep": closure.build_sweep(step), "knee_tf_newton": newton,
            "knee_tf_newton_batch": newton.map("knee_tf_newton_batch", "serial", closure.BATCH, [1, 2], [])}


class _CFunction:
    """One generated function of a loaded library, called with numpy buffers through ctypes.

    ``inputs`` and ``outputs`` are flat float arrays (column-major contents of each argument).
    """

    def __init__(self, lib, name: str, f: ca.Function):
        self.name = name
        self._f = getattr(lib, name)
        self._f.restype = ctypes.c_int
        self._f.argtypes = [ctypes.c_void_p] * 4 + [ctypes.c_int]
        ci = ctypes.c_longlong
        work = getattr(lib, name + "_work")
        work.argtypes = [ctypes.POINTER(ci)] * 4
        sz = [ci() for _ in range(4)]
        if work(*[ctypes.byref(s) for s in sz]) != 0:
            raise RuntimeError(f"{name}_work failed")
        sz_arg, sz_res, sz_iw, sz_w = (s.value for s in sz)
        checkout = getattr(lib, name + "_checkout", None)
        getattr(lib, name + "_incref")()
        self._mem = checkout() if checkout is not None else 0
        self.inputs = [np.zeros(f.numel_in(i)) for i in range(f.n_in())]
        self.outputs = [np.zeros(f.numel_out(i)) for i in range(f.n_out())]
        self._iw = np.zeros(max(sz_iw, 1), dtype=np.int64)
        self._w = np.zeros(max(sz_w, 1))
        argv = [a.ctypes.data for a in self.inputs] + [0] * (sz_arg - f.n_in())
        resv = [r.ctypes.data for r in self.outputs] + [0] * (sz_res - f.n_out())
        self._arg = (ctypes.c_void_p * len(argv))(*argv)
        self._res = (ctypes.c_void_p * len(resv))(*resv)
        self._call_args = (ctypes.addressof(self._arg), ctypes.addressof(self._res),
                           self._iw.ctypes.data, self._w.ctypes.data, self._mem)
        #: the object whose constant inputs (parameters) the buffers hold now (see ``Mechanism``)
        self.owner = None

    def call(self) -> None:
        """Evaluate with the current contents of :attr:`inputs` into :attr:`outputs`."""
        if self._f(*self._call_args) != 0:
            raise RuntimeError(f"{self.name} failed")


class _CasadiFunction:
    """The same interface as :class:`_CFunction`, evaluated by CasADi (no compiler needed)."""

    def __init__(self, f: ca.Function):
        self.name = f.name()
        self._f = f
        self._shapes = [f.size_in(i) for i in range(f.n_in())]
        self.inputs = [np.zeros(f.numel_in(i)) for i in range(f.n_in())]
        self.outputs = [np.zeros(f.numel_out(i)) for i in range(f.n_out())]
        self.owner = None

    def call(self) -> None:
        res = self._f(*[a.reshape(s, order="F") for a, s in zip(self.inputs, self._shapes)])
        if not isinstance(res, (list, tuple)):
            res = [res]
        for o, r in zip(self.outputs, res):
            o[...] = np.asarray(ca.DM(r)).ravel(order="F")


class _Shared:
    """What the threads share for one structure: the CasADi functions and the compiled library (or None)."""

    def __init__(self, kinds, has_pf, compile: bool | None):
        self.functions = build_functions(kinds, has_pf)
        self.library = None
        want = compile if compile is not None else os.environ.get("KNEE_NO_COMPILE", "") in ("", "0")
        if want:
            try:
                self.library = _compiled_library(self.functions)
            except (OSError, RuntimeError, subprocess.SubprocessError) as e:
                log.warning("compiling the mechanism failed (%s); using CasADi's virtual machine", e)
        self.lib = ctypes.CDLL(str(self.library)) if self.library is not None else None


class Backend:
    """The mechanism's numeric functions for one structure, with one thread's buffers: ``step``,
    ``sweep``, ``tf_newton``, ``tf_newton_batch``.

    Attributes
    ----------
    compiled : bool
        True when the functions run from the compiled shared library.
    library : Path or None
        The cached shared library in use.
    """

    def __init__(self, shared: _Shared):
        self.library = shared.library
        self.compiled = shared.lib is not None
        if self.compiled:
            wrap = {n: _CFunction(shared.lib, n, f) for n, f in shared.functions.items()}
        else:
            wrap = {n: _CasadiFunction(f) for n, f in shared.functions.items()}
        self.step = wrap["knee_step"]
        self.sweep = wrap["knee_sweep"]
        self.tf_newton = wrap["knee_tf_newton"]
        self.tf_newton_batch = wrap["knee_tf_newton_batch"]


_SHARED: dict = {}
_SHARED_LOCK = threading.Lock()
_THREAD = threading.local()


def backend(kinds, has_pf, compile: bool | None = None) -> Backend:
    """The calling thread's :class:`Backend` for a structure (memoised per thread; the functions and the
    library behind it are built once per process)."""
    key = (tuple(kinds), bool(has_pf), compile, os.environ.get("KNEE_NO_COMPILE", ""))
    mine = _THREAD.__dict__.setdefault("backends", {})
    if key not in mine:
        with _SHARED_LOCK:
            if key not in _SHARED:
                _SHARED[key] = _Shared(key[0], key[1], compile)
        mine[key] = Backend(_SHARED[key])
    return mine[key]


def new_backend(kinds, has_pf, compile: bool | None = None) -> Backend:
    """A :class:`Backend` of its own (nothing memoised): the functions generated and, when compiling, the
    library compiled or taken from the on-disk cache now."""
    return Backend(_Shared(tuple(kinds), bool(has_pf), compile))


def _unsafe(folder: Path) -> str:
    """Why a cache folder cannot be trusted ('' when it can): it must belong to this user (or root) and be
    writable by no one else, or another user could put a library there that this process would load."""
    st = folder.stat()
    if st.st_uid not in (os.getuid(), 0):
        return f"it belongs to another user (uid {st.st_uid})"
    if st.st_mode & 0o022:
        return f"it is writable by others (mode {st.st_mode & 0o777:o})"
    return ""


def _verified(so: Path) -> bool:
    """Whether a cached library matches the SHA-256 recorded when it was compiled (a truncated, corrupt or
    replaced file is compiled again), and is not writable by others."""
    side = so.with_name(so.name + ".sha256")
    try:
        if so.stat().st_mode & 0o022 or _unsafe(so):
            return False
        return side.read_text().strip() == hashlib.sha256(so.read_bytes()).hexdigest()
    except OSError:
        return False


def _compiled_library(funcs: dict[str, ca.Function]) -> Path | None:
    cc = find_compiler()
    if cc is None:
        log.warning("no C compiler found; the mechanism runs in CasADi's virtual machine")
        return None
    with tempfile.TemporaryDirectory(prefix="knee-cg-") as tmp:
        cg = ca.CodeGenerator("knee_mech.c", {"with_header": False})
        for f in funcs.values():
            cg.add(f)
        cg.generate(str(tmp) + os.sep)  # into the temporary folder (no change of working directory)
        src = Path(tmp) / "knee_mech.c"
        code = src.read_bytes()
        key = hashlib.sha256(code + " ".join(CFLAGS).encode() + GENERATOR_VERSION.encode()
                             + ca.__version__.encode()).hexdigest()[:20]
        d = cache_dir()
        so = d / f"knee_mech_{key}.so"
        d.mkdir(mode=0o700, parents=True, exist_ok=True)
        unsafe = _unsafe(d)
        if unsafe:
            # a library others could have replaced is never loaded: compile into a private folder instead
            log.warning("not using the solver cache %s: %s; compiling into a private folder", d, unsafe)
            d = Path(tempfile.mkdtemp(prefix="knee-private-cache-"))
            # removed when the process ends (a loaded library stays mapped): nothing is left in the temp folder
            atexit.register(shutil.rmtree, d, ignore_errors=True)
            so = d / so.name
        elif so.is_file() and _verified(so):
            return so
        out = Path(tmp) / "lib.so"
        proc = subprocess.run([cc, *CFLAGS, str(src), "-o", str(out), "-lm"], capture_output=True,
                              text=True, timeout=600)
        if proc.returncode != 0:
            raise RuntimeError(f"{cc} failed: {proc.stderr.strip().splitlines()[-1:]}")
        digest = hashlib.sha256(out.read_bytes()).hexdigest()
        for target, write in ((so.with_name(so.name + ".sha256"), lambda p: Path(p).write_text(digest + "\n")),
                              (so, lambda p: shutil.copyfile(out, p))):
            fd, part = tempfile.mkstemp(dir=d, suffix=".part")
            os.close(fd)
            write(part)
            os.chmod(part, 0o600 if target != so else 0o700)
            os.replace(part, target)  # atomic: concurrent processes never load a half-written library
        log.info("compiled mechanism functions into %s", so)
        return so
