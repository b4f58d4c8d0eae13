"""Dynamics models s_{t+1} = f(s_t, a_t): SINDy (and, later, a neural-network baseline)."""
