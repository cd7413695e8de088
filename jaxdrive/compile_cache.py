"""JAX's persistent compilation cache, on by default for ``jaxdrive train``, ``sample``, ``eval``
and ``demo``: a second run of the same config reads its compiled programs from disk instead of
compiling them again (the tiny train step compiles in 20-50 s on a CPU).

``train.compile_cache``: ``"default"`` (a folder under the user's cache directory:
``$JAXDRIVE_CACHE_DIR``, else ``$XDG_CACHE_HOME/jaxdrive/xla``, else ``~/.cache/jaxdrive/xla``;
a cache folder the user already gave JAX, by ``JAX_COMPILATION_CACHE_DIR`` or ``jax.config``,
is kept), a folder, or ``"off"``. :func:`counts` reads how many programs were looked up and found
(JAX's own monitoring events), so a run can say what the cache saved it.
"""

from __future__ import annotations

import os
import threading
from pathlib import Path

import jax

OFF = ("off", "none", "")
_counts = {"requests": 0, "hits": 0, "saved_seconds": 0.0}
_lock = threading.Lock()
_listening = False


def default_dir() -> Path:
    if os.environ.get("JAXDRIVE_CACHE_DIR"):
        return Path(os.environ["JAXDRIVE_CACHE_DIR"]) / "xla"
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "jaxdrive" / "xla"


def _on_event(event: str, **kwargs) -> None:
    with _lock:
        if event == "/jax/compilation_cache/compile_requests_use_cache":
            _counts["requests"] += 1
        elif event == "/jax/compilation_cache/cache_hits":
            _counts["hits"] += 1


def _on_duration(event: str, duration: float, **kwargs) -> None:
    if event == "/jax/compilation_cache/compile_time_saved_sec":
        with _lock:
            _counts["saved_seconds"] += float(duration)


def _listen() -> None:
    global _listening
    if not _listening:
        jax.monitoring.register_event_listener(_on_event)
        jax.monitoring.register_event_duration_secs_listener(_on_duration)
        _listening = True


def enable(setting: str = "default") -> Path | None:
    """Point JAX's persistent cache at ``setting`` (module docstring) before the first compile;
    returns the folder in use (None: off). Programs that compile in under a second are not
    stored (JAX's threshold); every size is. A ``ValueError`` names ``train.compile_cache`` when
    the folder cannot be created."""
    if not isinstance(setting, str):
        raise ValueError(f"train.compile_cache: expected 'default', 'off' or a folder, got {setting!r}")
    _listen()
    if setting.strip().lower() in OFF:
        jax.config.update("jax_enable_compilation_cache", False)
        return None
    given = jax.config.jax_compilation_cache_dir
    if setting == "default" and given:
        folder = Path(given)  # the user's own JAX setting wins over our default
    else:
        folder = default_dir() if setting == "default" else Path(setting).expanduser()
    try:
        folder.mkdir(parents=True, exist_ok=True)
    except OSError as e:
        raise ValueError(
            f"train.compile_cache: expected a folder that can be created, got {str(folder)!r} ({e.strerror})"
        ) from None
    jax.config.update("jax_enable_compilation_cache", True)
    if str(folder) != given:
        jax.config.update("jax_compilation_cache_dir", str(folder))
        try:  # a cache JAX already opened elsewhere is re-opened here
            from jax._src import compilation_cache

            compilation_cache.reset_cache()
        except (ImportError, AttributeError):
            pass
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
    return folder


def counts() -> dict:
    """``{"requests", "hits", "saved_seconds"}`` since this process started: programs looked up
    in the persistent cache, found there, and the compile seconds that saved (JAX's estimate)."""
    with _lock:
        return dict(_counts)


def describe(folder: Path | None, before: dict | None = None) -> str:
    """One line for a run's log: the folder and what the cache gave since ``before``."""
    if folder is None:
        return "XLA compilation cache off"
    now = counts()
    d = {k: now[k] - (before or {}).get(k, 0) for k in now}
    return (
        f"XLA compilation cache {folder}: {d['hits']} of {d['requests']} programs read from it "
        f"({d['saved_seconds']:.1f} s of compiling saved)"
    )
