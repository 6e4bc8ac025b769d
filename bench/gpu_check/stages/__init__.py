"""The GPU check's stages, one module each: a function (plan, deadline, args, save) -> StageResult run
in a child process of its own, except `tests` (pytest, run by the orchestrator). Each imports only
the standard library until it runs."""
