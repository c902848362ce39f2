"""Sim2Real: close the gap left after Real2Sim.

``hybrid`` learns the residual dynamics (real next state minus the identified simulator's) and
composes it with ``Sim`` into a differentiable hybrid simulator; ``residual`` is the zero-initialised
residual policy trained on real rollouts. Import the submodules directly.
"""
