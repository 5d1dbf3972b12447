"""`pvt view`: a live page of a cell (server.py; the page and its vendored uPlot in static/)."""
