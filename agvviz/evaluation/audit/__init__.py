"""The audit's mathematics: the bundle-adjustment problem, its estimate and report (values in, values out)."""
