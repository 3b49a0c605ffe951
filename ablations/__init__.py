"""Sweep collectors: ablation tables (collect.py) and the speed/accuracy chart (pareto.py) from multirun metrics.json files."""
