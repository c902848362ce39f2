"""A vmapped rollout sharded over two emulated CPU devices equals the one-device result.

Not bit for bit: each device compiles the rollout for its half batch, and XLA fuses and orders
float operations differently for another batch shape. Measured max |dqpos| over 8 rollouts of 20
push steps: 5.2e-7 in float32 (a few ulp), checked here in float64 to 1e-12.
"""

import subprocess
import sys
import textwrap

SCRIPT = textwrap.dedent("""
    import jax, jax.numpy as jnp, numpy as np
    import twinrl
    from twinrl.physics import Sim
    from twinrl.physics.parallel import batch_mesh, shard_batch
    assert len(jax.devices()) == 2, jax.devices()
    sim = Sim.load("push")
    B = 8
    rng = np.random.default_rng(0)
    qpos = np.tile(sim.mj_model.qpos0, (B, 1)); qpos[:, 0] = rng.uniform(-0.05, 0.05, B)
    acts = jnp.asarray(rng.uniform(-1, 1, (B, 20, 2)), jnp.float64)
    run = jax.jit(jax.vmap(lambda q, a: sim.rollout(sim.init(q), a)[1].qpos))
    one = run(jax.device_put(jnp.asarray(qpos, jnp.float64), jax.devices()[0]),
              jax.device_put(acts, jax.devices()[0]))
    q2, a2 = shard_batch((jnp.asarray(qpos, jnp.float64), acts), batch_mesh())
    two = run(q2, a2)
    assert len(two.sharding.device_set) == 2, two.sharding
    assert one.dtype == jnp.float64
    np.testing.assert_allclose(np.asarray(one), np.asarray(two), rtol=0, atol=1e-12)
    try:
        shard_batch(jnp.zeros((3, 2)))
    except ValueError as e:
        assert "multiple of 2" in str(e)
    else:
        raise AssertionError("odd batch was accepted")
    print("SHARDING-OK max-abs-diff", float(np.abs(np.asarray(one) - np.asarray(two)).max()))
""")


def test_two_emulated_devices_equal_one():
    import os
    # Same compiler flags as this process, plus the two emulated devices.
    flags = os.environ.get("XLA_FLAGS", "") + " --xla_force_host_platform_device_count=2"
    env = {"XLA_FLAGS": flags, "JAX_PLATFORMS": "cpu", "JAX_ENABLE_X64": "1"}
    out = subprocess.run([sys.executable, "-c", SCRIPT], capture_output=True, text=True,
                         env={**os.environ, **env}, timeout=600)
    assert out.returncode == 0, out.stderr[-3000:]
    assert "SHARDING-OK" in out.stdout, out.stdout[-2000:]
