import jax

from jaxest import compile_cache

# Tests work in float64 unless they cast to float32 themselves; jaxest never flips this on import.
jax.config.update("jax_enable_x64", True)


# JAX's persistent compilation cache only where JAXEST_COMPILATION_CACHE=1 asks for it
# (jaxest.compile_cache says why it is off by default); subprocesses and notebooks inherit it.
compile_cache.enable()
