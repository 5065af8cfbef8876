"""The fused CPU kernel's compiled extension (`_fused_correct`, built by setup.py from kernel/):
loading it, registering its handler with XLA, and what it declares it supports.

The extension is optional: without a C++ compiler at install it is not built and `correct` runs
the jax.numpy definition (`built`). A jaxlib older than the FFI headers it was compiled against
refuses its handler (`registration_refusal` says so, once).
"""

from __future__ import annotations

import functools
import logging
from collections.abc import Callable

import jax

try:  # built by setup.py as an optional extension
    from . import _fused_correct
except ImportError:  # pragma: no cover - exercised only where the build failed
    _fused_correct = None

#: The name the kernel is registered under with XLA (jax.ffi).
TARGET = "spherejax_fused_correct"

_log = logging.getLogger("spherejax._engine.fused")


def _try_register(register: Callable) -> str | None:
    """Register the kernel with XLA through `register` (jax.ffi.register_ffi_target's signature);
    None if XLA took it, else why not, in one line.

    The CPU backend is started first: before it exists jax only queues a registration, and a
    handler XLA refuses would then fail whatever first starts the backend instead of here.
    XLA refuses a handler compiled against a newer FFI API than its own (setup.py).
    """
    try:
        jax.devices("cpu")
    except RuntimeError as error:  # JAX_PLATFORMS without "cpu" (a GPU-only process)
        return f"the fused kernel runs on XLA's CPU backend, which this process does not have ({error})"
    try:
        register(TARGET, _fused_correct.handler(), platform="cpu")
    except Exception as error:  # noqa: BLE001 -- XLA's refusal (JaxRuntimeError) or any other: the kernel is then not used
        import jaxlib

        major, minor = _fused_correct.ffi_api_version()
        message = " ".join(str(error).split("\n")[0].split()).rstrip(".")
        reason = (
            f"the fused kernel (XLA FFI API {major}.{minor}) was refused by jaxlib {jaxlib.__version__}: {message}; "
            "correct runs its jax.numpy path (the same numbers, slower). Rebuild the kernel against this jaxlib: "
            "pip install --no-build-isolation --force-reinstall --no-deps spherejax (from its source)"
        )
        _log.warning("%s", reason)  # unexpected, and it costs speed: said once (`registration_refusal` caches)
        return reason
    return None


@functools.cache
def registration_refusal() -> str | None:
    """Registers the kernel once per process: None if registered, else the reason it is not."""
    if _fused_correct is None:
        return "the fused kernel was not built (no C++17 compiler or no jaxlib headers at install: setup.py)"
    return _try_register(jax.ffi.register_ffi_target)


def register() -> bool:
    """Registers the kernel with XLA once per process: True if XLA took it."""
    return registration_refusal() is None


def built() -> bool:
    """True if the compiled kernel was built and imported."""
    return _fused_correct is not None


@functools.cache
def supported_variants() -> tuple[str, ...]:
    """The variants this build has and this CPU runs, widest first ("generic" always), or () where
    the kernel was not built."""
    return tuple(_fused_correct.supported_variants()) if _fused_correct is not None else ()


@functools.cache
def capabilities() -> dict:
    """What the compiled kernel declares it supports (module.cc, `capabilities`), or {} where it
    was not built."""
    if _fused_correct is None or not hasattr(_fused_correct, "capabilities"):
        return {}
    return dict(_fused_correct.capabilities())


__all__ = ["TARGET", "built", "capabilities", "register", "registration_refusal", "supported_variants"]
