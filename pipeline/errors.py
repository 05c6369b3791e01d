"""Domain errors. The CLI turns these into a readable message and exit code 1, never a traceback."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path


@dataclass(frozen=True)
class Problem:
    """One thing wrong with an input: where it is, what is wrong, and how to fix it."""

    file: str
    message: str
    row: int | None = None  # 1-based line number in the file (a CSV header is line 1)
    fix: str | None = None
    key: str | None = None

    def __str__(self) -> str:
        where = self.file
        if self.row is not None:
            where += f", line {self.row}"
        if self.key is not None:
            where += f", key '{self.key}'"
        text = f"{where}: {self.message}"
        if self.fix:
            text += f" (fix: {self.fix})"
        return text


class Problems:
    """Collects problems while a validator keeps going, so the user sees all of them at once."""

    def __init__(self) -> None:
        self.items: list[Problem] = []
        self.warnings: list[Problem] = []

    def add(
        self, file, message: str, *, row: int | None = None, fix: str | None = None, key: str | None = None
    ) -> None:
        self.items.append(Problem(str(file), message, row=row, fix=fix, key=key))

    def warn(self, file, message: str, *, row: int | None = None, fix: str | None = None) -> None:
        self.warnings.append(Problem(str(file), message, row=row, fix=fix))

    def extend(self, problems: list[Problem]) -> None:
        self.items.extend(problems)

    def __bool__(self) -> bool:
        return bool(self.items)

    def raise_if_any(self, summary: str) -> None:
        if self.items:
            raise InputError(summary, self.items)


class SitelocError(Exception):
    """Base class of every error the CLI reports without a traceback."""


class ConfigError(SitelocError):
    """A config file or value is wrong; the message names the file and the key."""


class InputError(SitelocError):
    """Input data is wrong. Carries every problem found, not only the first."""

    def __init__(self, summary: str, problems: list[Problem] | None = None):
        self.summary = summary
        self.problems = list(problems or [])
        super().__init__(self.render())

    def render(self) -> str:
        lines = [self.summary]
        if len(self.problems) > 1:
            lines[0] += f" ({len(self.problems)} problems)"
        lines.extend(f"  - {p}" for p in self.problems)
        return "\n".join(lines)


class OutputOverlapsInputError(SitelocError):
    """An output that would replace, sit inside or contain one of the command's inputs."""


class RuntimeInputError(SitelocError, ValueError):
    """A value handed to the runtime's public API (a scan, odometry, an image, a pose) that it cannot use."""


def excerpt(value: object, limit: int = 60) -> str:
    """A short, printable quotation of bad input: control bytes escaped, at most `limit` characters.

    Messages quote what the user gave so they can find it; a 10 MB line or a terminal escape sequence from a
    log must not reach the terminal whole.
    """
    text = value.decode("utf-8", "backslashreplace") if isinstance(value, bytes | bytearray) else str(value)
    out = []
    for ch in text[: limit + 1]:
        code = ord(ch)
        if ch in "\t\n\r" or code < 0x20 or 0x7F <= code < 0xA0:
            out.append(ch.encode("unicode_escape").decode("ascii"))
        else:
            out.append(ch)
    quoted = "".join(out)
    if len(text) > limit or len(quoted) > limit:
        quoted = quoted[:limit] + f"... ({len(text)} characters)"
    return quoted


class OutputExistsError(SitelocError):
    def __init__(self, path: Path):
        super().__init__(
            f"{path} already exists; pass --force to replace it (the old one is kept until the new one is complete)"
        )
