"""Analysis tools, each run as `python -m realityavatar.analysis.<tool>`: sweep tables (collect), the
speed/accuracy chart and the Gaussian budget's choice (pareto), per-frame geometry probes (probe), the stability
report (stability), frame strips (frames) and the garment's ceiling, Gaussians glued to the simulated cloth (oracle).
Their outputs go to ablations/results/ (see its README.md)."""
