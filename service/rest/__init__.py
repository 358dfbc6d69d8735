"""REST adapter (FastAPI)."""
