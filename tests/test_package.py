"""``import twinrl``: sub-packages as attributes, imported lazily."""

import subprocess
import sys


def test_subpackages_are_attributes_imported_on_first_use():
    code = ("import sys, twinrl\n"
            "assert 'twinrl.learn' not in sys.modules and 'twinrl.envs' not in sys.modules\n"
            "assert {'envs', 'physics', 'learn', 'real'} <= set(dir(twinrl))\n"
            "assert callable(twinrl.envs.make) and twinrl.physics.Sim and twinrl.real2sim\n"
            "assert 'twinrl.envs' in sys.modules and 'twinrl.learn' not in sys.modules\n"
            "assert twinrl.learn.__name__ == 'twinrl.learn' and twinrl.report.print_table\n"
            "try:\n"
            "    twinrl.nosuch\n"
            "except AttributeError as e:\n"
            "    assert \"no attribute 'nosuch'\" in str(e)\n"
            "else:\n"
            "    raise SystemExit('twinrl.nosuch did not raise')\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 0, out.stderr[-3000:]


def _after_import(pre: str = "", **env_vars) -> subprocess.Popen:
    import os

    env = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", "TWINRL_XLA_FLAGS")}
    env.update(env_vars, TWINRL_CACHE_DIR="off")
    code = (pre + "import os, twinrl, jax, jax.numpy as jnp\n"
            "jnp.ones(1).block_until_ready()\n"
            "print(os.environ.get('XLA_FLAGS', ''))\n")
    return subprocess.Popen([sys.executable, "-W", "always", "-c", code], stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True, env=env)


def _flags_after_import(pre: str = "", **env_vars) -> subprocess.CompletedProcess:
    """A fresh process that runs ``pre``, imports twinrl and runs a JAX computation: its
    ``XLA_FLAGS`` then (stdout) and what it said (stderr)."""
    return _finished(_after_import(pre, **env_vars))


def _finished(proc: subprocess.Popen) -> subprocess.CompletedProcess:
    out, err = proc.communicate(timeout=120)
    return subprocess.CompletedProcess(proc.args, proc.returncode, out, err)


def test_import_turns_xla_cpu_fusion_emitters_off_unless_the_user_chose():
    # MJX's kinematics runs ~100x slower on deep chains with them on (``import twinrl``)
    out = _flags_after_import(XLA_FLAGS="--xla_cpu_multi_thread_eigen=true")
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.split() == ["--xla_cpu_multi_thread_eigen=true",
                                  "--xla_cpu_use_fusion_emitters=false"]
    kept = _flags_after_import(XLA_FLAGS="--xla_cpu_use_fusion_emitters=true")
    assert kept.stdout.split() == ["--xla_cpu_use_fusion_emitters=true"]
    off = _flags_after_import(TWINRL_XLA_FLAGS="off")
    assert off.stdout.strip() == ""
    late = _flags_after_import(pre="import jax.numpy as jnp; jnp.zeros(1).block_until_ready()\n")
    assert late.stdout.strip() == ""  # too late to change: said once, in one line
    said = [ln for ln in late.stderr.splitlines() if "fusion emitters stay on" in ln]
    assert len(said) == 1 and "import twinrl first" in said[0]


def test_cpu_flags_are_added_only_where_xla_knows_them():
    # jaxlib 0.11.2's XLA aborts the process on --xla_cpu_use_fusion_emitters ("Unknown flag"):
    # under a jaxlib that says it is of a later series than the pinned one (0.9, whose import
    # the test above runs) the import leaves XLA_FLAGS as the user set them; under an older
    # series it adds the flag
    versions = {"0.4.38": True, "0.10.0": False, "0.11.2": False, "1.0.0.dev20270101": False}
    procs = {v: _after_import(pre=f"import jaxlib; jaxlib.__version__ = {v!r}\n",
                              XLA_FLAGS="--xla_cpu_multi_thread_eigen=true") for v in versions}
    for version, added in versions.items():
        out = _finished(procs[version])
        assert out.returncode == 0, (version, out.stderr[-2000:])
        assert out.stdout.split() == ["--xla_cpu_multi_thread_eigen=true"] + (
            ["--xla_cpu_use_fusion_emitters=false"] if added else []), (version, out.stdout)


def test_jits_without_mjx_get_the_fusion_emitters_back_only_where_twinrl_turned_them_off():
    # visual fits compile with them on (their Adam step 2.6x faster); a user's choice stands
    import os

    code = ("import twinrl, jax, jax.numpy as jnp\n"
            "from twinrl.jaxconfig import image_compiler_options as o\n"
            "f = jax.jit(lambda x: jax.nn.logsumexp(x, 1), compiler_options=o())\n"
            "assert abs(float(f(jnp.zeros((3, 4)))[0]) - float(jnp.log(4.0))) < 1e-6\n"
            "print(o())\n")
    env = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", "TWINRL_XLA_FLAGS")}
    seen = {}
    for name, extra in [("added", {}), ("off", {"TWINRL_XLA_FLAGS": "off"}),
                        ("chosen", {"XLA_FLAGS": "--xla_cpu_use_fusion_emitters=false"})]:
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                             env={**env, **extra, "TWINRL_CACHE_DIR": "off"}, timeout=120)
        assert out.returncode == 0, out.stderr[-2000:]
        seen[name] = out.stdout.strip()
    assert seen == {"added": "{'xla_cpu_use_fusion_emitters': True}", "off": "None",
                    "chosen": "None"}
