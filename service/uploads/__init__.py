"""Untrusted uploads: multipart forms and image files read and checked in sandboxed decoder
processes, the rectifiers of raw pairs' cameras, and the bytes and streams the server holds at once."""
