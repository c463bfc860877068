"""The project's C++ extension (stm/csrc), built from its own sources on first use and cached, and which step kernel
runs (`step_kernel`).

torch.utils.cpp_extension.load compiles the sources with ninja into the torch extensions folder
(TORCH_EXTENSIONS_DIR, by default under the user's cache) and, in later processes, only loads what it built
there (it rebuilds when a source or flag changes; a file lock keeps parallel processes from building twice).
Where no compiler or ninja is found, or the build fails, `self_fed_extension` warns once and returns None:
the callers fall back to the pure-PyTorch path, which computes the same. With ACRMDN_REQUIRE_CPP=1 (CI: the nox
tests session sets it) a failed build raises instead, so a broken toolchain fails the tests instead of skipping
the C++ ones.
"""

from __future__ import annotations

import functools
import logging
import os
import shutil
import time
import warnings
from pathlib import Path

log = logging.getLogger(__name__)

SOURCES = [Path(__file__).parent / "csrc" / name
           for name in ("self_fed.cpp", "segment.cpp", "lstm_step.cpp", "feedback_state.cpp", "products.cpp",
                         "vec_math.cpp", "mdn_nll.cpp")]
NAME = "stm_self_fed"
REQUIRE = "ACRMDN_REQUIRE_CPP"  # set (not "0"): the extension must build, a failed build raises
load_seconds: float | None = None  # how long loading took in this process (a first build: about a minute)


def _find_ninja() -> None:
    """torch runs `ninja` from PATH; the ninja wheel (a dependency) puts it in the environment's bin, which is on
    PATH only in an activated environment: add its folder."""
    if shutil.which("ninja") is None:
        try:
            import ninja  # type: ignore[import-untyped]

            os.environ["PATH"] = ninja.BIN_DIR + os.pathsep + os.environ.get("PATH", "")
        except ImportError:
            pass


@functools.cache
def self_fed_extension():
    """The compiled module (segment_*, sequence_* and mdn_nll_* forward and backward), or None (one warning) where it
    cannot be built. A first build takes about a minute on two cores (logged at INFO with the load time, kept in
    `load_seconds`); later processes load the cached build in well under a second."""
    global load_seconds
    try:
        from torch.utils import cpp_extension

        _find_ninja()
        cpp_extension.verify_ninja_availability()
        compiler = os.environ.get("CXX", "c++")
        if shutil.which(compiler) is None:
            raise RuntimeError(f"no C++ compiler ({compiler}) on PATH")
        start = time.perf_counter()
        ext = cpp_extension.load(NAME, [str(p) for p in SOURCES], extra_cflags=["-O3"], verbose=False)
    except Exception as exc:  # a missing toolchain or a failed build: the Python path computes the same
        if required():
            raise RuntimeError(f"{REQUIRE} is set and the C++ step kernel cannot be built: {type(exc).__name__}: "
                               f"{exc}") from exc
        warnings.warn(f"the C++ step kernel is unavailable ({type(exc).__name__}: {exc}); using the Python step",
                      RuntimeWarning, stacklevel=2)
        return None
    load_seconds = time.perf_counter() - start
    log.info("C++ step kernel ready in %.1f s (built, or loaded from %s)", load_seconds, ext.__file__)
    return ext


def required() -> bool:
    """Whether the extension must build (ACRMDN_REQUIRE_CPP set, and not to 0)."""
    return os.environ.get(REQUIRE, "") not in ("", "0")


def step_kernel(requested: str, device_type: str = "cpu") -> str:
    """The step kernel that runs for TrainConfig.step_kernel `requested` on a device of this type: "python" as
    asked; "auto" (the default): "cpp" where the extension builds, else "python" (self_fed_extension warned once);
    "cpp": "cpp", a RuntimeError where the extension cannot be built. The C++ kernels run on the CPU: elsewhere
    "python" (a GPU runs the Python steps, captured as a CUDA graph)."""
    if requested == "python" or device_type != "cpu":
        return "python"
    if self_fed_extension() is not None:
        return "cpp"
    if requested == "cpp":
        raise RuntimeError("train.step_kernel=cpp, but the C++ extension cannot be built here (see the warning "
                           "above); use step_kernel auto or python")
    return "python"
