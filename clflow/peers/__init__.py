"""Peers that clflow's benchmarks run in the same process, on the same inputs, so that a
figure comes with the figure it is judged against (optional extras: ``clflow[peers]``)."""
