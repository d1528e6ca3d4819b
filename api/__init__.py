"""BranchRange's HTTP service (FastAPI): `create_app` builds it; `branchrange serve` runs it."""

from api.app import create_app

__all__ = ["create_app"]
