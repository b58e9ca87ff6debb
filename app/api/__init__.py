"""HTTP API: ``main.api_router`` aggregates one router per resource under ``routes/``."""
