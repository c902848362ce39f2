"""The SAM-RL manipulation suite (Lv et al., RSS 2023): a Panda-kinematics arm with a tool at its
flange and a camera on a movable mount, and the tasks peg insertion, spatula flipping and needle
threading. The robot is one module per concern (``kinematics``, ``controller``, ``mount``,
``perception``, ``task``; ``twinrl.envs.arm.base`` re-exports them); one module per task, its MJCF
beside it."""
