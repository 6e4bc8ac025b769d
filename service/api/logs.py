"""Structured logs: one JSON object per line on stderr, carrying the request id."""

from __future__ import annotations

import json
import logging
import sys
import warnings
from contextvars import ContextVar
from datetime import UTC, datetime
from typing import TextIO

request_id_var: ContextVar[str | None] = ContextVar("request_id", default=None)

# Attributes every LogRecord has; anything else on a record came from `extra=` and is logged.
_STANDARD_ATTRS = set(logging.makeLogRecord({}).__dict__) | {"message", "asctime", "color_message"}


class JsonFormatter(logging.Formatter):
    """Formats a record as JSON: time, level, logger, message, request_id, any `extra` fields and
    the traceback when there is one."""

    def format(self, record: logging.LogRecord) -> str:
        entry: dict[str, object] = {
            "time": datetime.fromtimestamp(record.created, UTC).isoformat(timespec="milliseconds"),
            "level": record.levelname.lower(),
            "logger": record.name,
            "message": record.getMessage(),
        }
        request_id = request_id_var.get()
        if request_id is not None:
            entry["request_id"] = request_id
        entry.update({k: v for k, v in record.__dict__.items() if k not in _STANDARD_ATTRS})
        if record.exc_info:
            entry["traceback"] = self.formatException(record.exc_info)
        return json.dumps(entry, default=str)


def log_warning(
    message: Warning | str,
    category: type[Warning],
    filename: str,
    lineno: int,
    file: TextIO | None = None,
    line: str | None = None,
) -> None:
    """A Python warning as one line of the `py.warnings` log: its category and message, where it
    came from in `location` (`logging.captureWarnings` would log the source line too)."""
    logging.getLogger("py.warnings").warning(
        "%s: %s", category.__name__, message, extra={"location": f"{filename}:{lineno}"}
    )


def configure_logging(level: str) -> None:
    """JSON logs for the `crestereo_pp` loggers (service, model) (the OpenVINO exports: when each fast path is
    ready), Python warnings and uvicorn's server log; uvicorn's own access log is turned off
    because the service writes a JSON access line per request."""
    handler = logging.StreamHandler(sys.stderr)
    handler.setFormatter(JsonFormatter())
    for name in ("crestereo_pp", "py.warnings"):  # py.warnings: Python warnings, e.g. untrained weights
        logger = logging.getLogger(name)
        logger.handlers = [handler]
        logger.setLevel(level.upper())
        logger.propagate = False
    warnings.showwarning = log_warning
    for uvicorn_handler in logging.getLogger("uvicorn.error").handlers + logging.getLogger("uvicorn").handlers:
        uvicorn_handler.setFormatter(JsonFormatter())
    logging.getLogger("uvicorn.access").disabled = True
