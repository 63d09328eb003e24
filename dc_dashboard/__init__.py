"""``dc dashboard``: what DC stored in PostgreSQL and S3 and how its delivery is doing, in a browser.

Server-rendered HTML with inline SVG charts on the standard library's HTTP server: every view is a
URL whose query string holds the filters (docs/dashboard.md says why this and not Streamlit).
"""
