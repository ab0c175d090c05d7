"""Baseline training configs (one YAML each), shipped as package data of ``racebench.configs``: ``--config NAME``."""
