"""Fixtures of the web page tests (they and the helpers live in `web_helpers.py`)."""

from web_helpers import browser, default_server, web  # noqa: F401  (pytest finds fixtures by name)
