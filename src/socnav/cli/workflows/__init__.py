"""The heavier steps some commands run (they import pandas, torch or matplotlib): loaded inside the commands, never
by `socnav --help`. `demo` (the tour), `animation` (one episode with its uncertainty drawn live), `tune` (Optuna).
"""
