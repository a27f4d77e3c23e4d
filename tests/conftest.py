import os
from pathlib import Path

import jax

# Tests work in float64 unless they cast to float32 themselves; jaxest never flips this on import.
jax.config.update("jax_enable_x64", True)


def jax_cache_dir() -> Path:
    """JAX's persistent compilation cache, outside the clone: $JAX_COMPILATION_CACHE_DIR, else
    $XDG_CACHE_HOME/jaxest/jax, else ~/.cache/jaxest/jax (the Makefile exports the same path)."""
    explicit = os.environ.get("JAX_COMPILATION_CACHE_DIR")
    if explicit:
        return Path(explicit)
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "jaxest" / "jax"


# Reload compiled programs across test sessions (a second `make test` skips most compilation).
# jaxlib 0.10 rejects entries on some AVX-512 hosts ("Target machine feature ... is not
# supported"): it then logs a warning and compiles afresh, so results never depend on the cache.
jax.config.update("jax_compilation_cache_dir", str(jax_cache_dir()))
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.2)
