"""The API's routers, one per concern: pages, status (health, channels, events), curves
(coefficients, Allan, PSD) and the model (diagnosis, model changes, refits)."""
