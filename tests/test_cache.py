"""enable_compilation_cache: opt-in, effective after earlier compilations, and the only
place the library touches JAX's configuration."""

import json
import subprocess
import sys

SCRIPT = """
import json, pathlib, sys
import jax
import jax.numpy as jnp
import elastic_jax as ej
before = jax.config.jax_compilation_cache_dir  # importing the library set nothing
jax.jit(lambda x: jnp.sin(x) * 2)(1.0)  # JAX settles on "no cache" here
first = ej.enable_compilation_cache(sys.argv[1] + "/a", min_compile_time_s=0)
jax.jit(lambda x: jnp.cos(x) + 3)(1.0)
path = ej.enable_compilation_cache(sys.argv[1] + "/b", min_compile_time_s=0)
jax.jit(lambda x: jnp.tan(x) - 4)(1.0)
print(json.dumps({"before": before, "after": jax.config.jax_compilation_cache_dir,
                  "path": str(path), "entries": len(list(pathlib.Path(path).iterdir())),
                  "first": len(list(first.iterdir()))}))
"""


def test_the_cache_is_opt_in_and_works_after_earlier_compilations(tmp_path):
    run = subprocess.run(
        [sys.executable, "-c", SCRIPT, str(tmp_path / "cache")],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert run.returncode == 0, run.stderr[-2000:]
    out = json.loads(run.stdout.strip().splitlines()[-1])
    assert out["before"] is None
    assert out["after"] == out["path"] == str((tmp_path / "cache" / "b").resolve())
    # Each directory holds what was compiled while it was the cache: a second call moves
    # the cache (JAX alone would keep the directory it opened first).
    assert out["first"] >= 1 and out["entries"] >= 1
