"""Tests of ``twinrl.real``."""
