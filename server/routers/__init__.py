"""The /v1 API's routers: assets, jobs, and operations (health, readiness, metrics)."""
