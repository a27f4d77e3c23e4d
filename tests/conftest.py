import jax

from jaxest import compile_cache

# Tests work in float64 unless they cast to float32 themselves; jaxest never flips this on import.
jax.config.update("jax_enable_x64", True)


# Reload compiled programs across test sessions (a second `make test` skips most compilation), in
# a directory per processor (jaxest.compile_cache); subprocesses and notebooks inherit it.
# jaxlib 0.10 rejects entries on some AVX-512 hosts ("Target machine feature ... is not
# supported"): it then logs a warning and compiles afresh, so results never depend on the cache.
compile_cache.enable()
