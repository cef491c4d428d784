"""Simulated worlds used at run time as well as by the generators.

A world here is code a run needs after its data exist (the planning task
places actions in the PHYRE-like scenes and simulates them), so it cannot
live with the writers in `data/write/`, which only the data stage
runs; the generators (datasets/) import it from here.
"""
