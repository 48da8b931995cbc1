"""Layer 3, simulation: loop banks and offline runs, recordings, limit cycles, figures."""
