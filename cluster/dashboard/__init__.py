"""The live dashboard: panel definitions, the exporter scraper, the HTTP server, the page."""
