"""Guidance video, observed optical flow, simulated flow, flow losses and metrics."""
