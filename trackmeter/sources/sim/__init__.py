"""The simulator: satellite mock-up, stereo renderer, rigid-body dynamics and scenarios."""
