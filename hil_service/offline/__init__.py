"""Working from logs: replay through the live path, series, reports and figures."""
