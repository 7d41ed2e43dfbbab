"""The persistent compilation cache: where it lives, and that a second process uses it."""

import os
import subprocess
import sys

from jaxrefl import compile_cache

_PROGRAM = """
import sys, jax, jax.numpy as jnp
from jaxrefl.compile_cache import enable
print(enable())
print(float(jax.jit(lambda x: jnp.sin(x) * 3.0 + x ** 2)(jnp.arange(5.0)).sum()))
"""


def test_cache_dir_follows_the_environment(monkeypatch, tmp_path):
    monkeypatch.setenv("JAXREFL_CACHE", str(tmp_path / "c"))
    assert compile_cache.cache_dir() == os.path.join(str(tmp_path / "c"), "jax")
    monkeypatch.setenv("JAXREFL_CACHE", "off")
    assert compile_cache.cache_dir() is None and compile_cache.base_dir() is None
    monkeypatch.delenv("JAXREFL_CACHE")
    monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
    assert compile_cache.cache_dir() == os.path.join(str(tmp_path / "xdg"), "jaxrefl", "jax")


def _run(env):
    out = subprocess.run([sys.executable, "-c", _PROGRAM], env=env, capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr
    return out.stdout.split()


def test_a_second_process_reads_what_the_first_compiled(tmp_path):
    env = {k: v for k, v in os.environ.items() if not k.startswith("JAX_COMPILATION_CACHE")}
    env["JAXREFL_CACHE"] = str(tmp_path / "cache")
    first = _run(env)
    assert first[0] == str(tmp_path / "cache" / "jax")
    entries = os.listdir(tmp_path / "cache" / "jax")
    assert entries  # the program was written
    second = _run(env)
    assert second == first and sorted(os.listdir(tmp_path / "cache" / "jax")) == sorted(entries)  # read, not rewritten
    env["JAXREFL_CACHE"] = "off"
    assert _run(env)[0] == "None"
