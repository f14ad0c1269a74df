"""The web app: the JSON API under /api (OpenAPI at /docs) and, later, the HTML pages."""
