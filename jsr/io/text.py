"""Reading the small text files a user hands over (lists, calibration, config, trajectories)."""

from __future__ import annotations

from pathlib import Path

from jsr.errors import InputError, JsrError


def read_user_text(path: Path, what: str, error: type[JsrError] = InputError) -> str:
    """The UTF-8 text of ``path``; a missing, unreadable or binary file raises ``error``."""
    path = Path(path)
    if path.is_dir():
        raise error(f"{what} {path} is a folder; give a file")
    try:
        return path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise error(f"{what} {path} does not exist") from None
    except UnicodeDecodeError:
        raise error(f"{what} {path} is not a text file") from None
    except OSError as os_error:
        raise error(f"cannot read {what} {path}: {os_error.strerror}") from None


def describe_yaml_error(error: Exception) -> str:
    """One line for a PyYAML parse error: where (1-based line and column) and what."""
    mark = getattr(error, "problem_mark", None)
    problem = getattr(error, "problem", None) or str(error).splitlines()[0]
    if mark is None:
        return problem
    return f"line {mark.line + 1}, column {mark.column + 1}: {problem}"
