"""The one rule for study names, and the folders named after them.

A study name is letters (A-Z, a-z), digits, '-', '_', '.', '@' and '+', starting with a letter or digit, at most
100 characters. Every entry point checks the names it is given (`--study-name`, `--study`, `--set study_name=`,
an export's runs.json) and the names it derives from them (milestones' "<study>-milestones", a sweep's
"<task>-<variant>-<profile>", a profile file's stem) with `check_study_name`; a name that breaks the rule is one
error line (exit code 2), never cleaned into another name: two names that cleaned to the same folder would
share it, and "." or ".." would be the folder above.

A name that obeys the rule is a folder name as it stands (no '/', never "." or ".."), so a study's outputs go to
ROOT/<name> (reports/out, reports/studies, snapshots). `study_folder` still resolves that folder and checks that
it lies inside its root before anything is written or deleted there: a symbolic link in the way is refused too.
"""

from __future__ import annotations

import re
from pathlib import Path

from experiments.config_errors import ConfigError

MAX_LENGTH = 100
RULE = (f"a study name is letters, digits, '-', '_', '.', '@' and '+', starting with a letter or digit, "
        f"at most {MAX_LENGTH} characters")
_VALID = re.compile(rf"[A-Za-z0-9][A-Za-z0-9_.@+-]{{0,{MAX_LENGTH - 1}}}")


class StudyNameError(ConfigError):
    """A study name that breaks the rule; str() is the one-line message (exit code 2)."""


class UnsafeFolder(ValueError):
    """A study's folder that would lie outside its root; str() is the one-line message (exit code 2)."""


def is_study_name(name: object) -> bool:
    return isinstance(name, str) and _VALID.fullmatch(name) is not None


def shown(name: object, limit: int = 60) -> str:
    """`name` for an error line: repr (so a line break in it cannot split the line), cut at `limit` characters."""
    text = repr(name)
    return text if len(text) <= limit else f"{text[:limit]}...' ({len(name) if isinstance(name, str) else '?'} chars)"


def check_study_name(name: object, what: str = "study name") -> str:
    """`name` when it obeys the rule, else StudyNameError '<what> <name>: <the rule>'."""
    if not is_study_name(name):
        raise StudyNameError(f"{what} {shown(name)}: {RULE}")
    return name


def optional_study_name(name: str) -> str:
    """A config field's study name: "" (derive it) or one that obeys the rule (a pydantic validator's ValueError
    otherwise, which experiments.config_errors turns into '<field>: <name> is not allowed; <the rule>')."""
    if name and not is_study_name(name):
        raise ValueError(f"{shown(name)} is not allowed; {RULE}")
    return name


def study_folder(root: Path, name: str, what: str = "study name") -> Path:
    """ROOT/NAME for the study's files: the name checked, and the folder (resolved: links followed) checked to lie
    inside the resolved root. Nothing is created."""
    check_study_name(name, what)
    base = Path(root).resolve()
    folder = (base / name).resolve()
    if folder.parent != base:
        raise UnsafeFolder(f"{Path(root) / name} resolves to {folder}, outside {base} (a symbolic link?); "
                           "remove the link or choose another --out")
    return Path(root) / name


def inside(root: Path, path: Path) -> Path:
    """`path` when it resolves inside the resolved `root` (a file a command is about to write or delete), else
    UnsafeFolder."""
    base, target = Path(root).resolve(), Path(path).resolve()
    if target == base or base not in target.parents:
        raise UnsafeFolder(f"{path} resolves to {target}, outside {base}; refusing to write or delete it")
    return Path(path)
