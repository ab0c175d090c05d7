"""Built-in track files (S, J, Circle), shipped as package data of ``racebench.tracks``."""
