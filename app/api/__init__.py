"""The FastAPI server (thin routers; the engine never imports this package)."""
