"""A 2-link capsule arm (hinges with limits, motors) falling onto and pressing a free box on a
plane: gradients through limits, arm-box and box-floor contacts (float64, T = 30)."""

from tests.physics._foreign import check_foreign_scene


def test_arm_pressing_a_box_passes_gradcheck_with_every_group_judged(x64):
    check_foreign_scene("arm_press")
