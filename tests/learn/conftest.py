"""Fixtures the learner tests share."""

import pytest

from tests.learn._peg import peg_image_actor


@pytest.fixture(scope="module")
def peg():
    """The sensing tests' short peg insertion and untrained image actor (``tests/learn/_peg.py``),
    built once per module."""
    return peg_image_actor()
