"""Routers by concern: `estimate` (POST /estimate, /disparity) and `status` (health, version, metrics, latest)."""
