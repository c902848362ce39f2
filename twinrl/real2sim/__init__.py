"""Real2Sim: fit the simulation to what the real system recorded.

``sysid`` fits ``PhysParams`` (and the action latency) to recorded transitions by gradient descent
through the simulator (multiple shooting over short windows); ``visual`` fits the camera and the
objects' pose, size and colour to recorded RGB-D + segmentation images through ``twinrl.render``;
``baselines`` holds CMA-ES on the same losses. Import the submodules directly.
"""
