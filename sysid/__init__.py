"""System identification and modelling built on ``integrators``."""
