"""A one-joint arm written for the tests as a user would write their robot's MJCF: a hinge in
the horizontal plane (no gravity torque) with a named motor, no contact, no camera -- cheap to
compile. ``tests/envs/test_mjcf_reward.py`` learns in it, ``tests/real/test_twin_mjcf.py`` gives
it a real twin."""

ARM = """<mujoco model="turntable">
  <option timestep="0.01"/>
  <worldbody>
    <body name="link">
      <joint name="hinge" type="hinge" axis="0 0 1" damping="0.2"/>
      <geom type="capsule" fromto="0 0 0 0.3 0 0" size="0.03" mass="0.5"/>
    </body>
  </worldbody>
  <actuator><motor name="motor" joint="hinge" gear="1" ctrlrange="-1 1"/></actuator>
</mujoco>"""
