"""The documentation against the code: the generated reference pages are those the code
generates now (a flag or field without a docstring stops the generator), every Python block of
the README and docs/ runs as pasted, every ``td3-jax`` command in them uses flags the command
has, every test the algorithm page names exists, and the metrics page names every field of a
real run's records."""

from __future__ import annotations

import contextlib
import dataclasses
import importlib.util
import io
import re
import shlex
import sys
from pathlib import Path

import pytest
from support import TINY_FLAGS, main, read_records

from td3_jax.config.schema import TrainConfig

ROOT = Path(__file__).resolve().parents[1]
DOCS = ROOT / "docs"
README = ROOT / "README.md"
#: The marker comments a Python block is preceded by (the line before its fence).
FAST, SLOW = "<!-- runnable -->", "<!-- runnable: slow -->"


def load_generator():
    """``docs/gen_reference.py`` as a module (docs/ is not a package)."""
    spec = importlib.util.spec_from_file_location("gen_reference", DOCS / "gen_reference.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules["gen_reference"] = module
    spec.loader.exec_module(module)
    return module


gen = load_generator()


def markdown_files() -> list[Path]:
    """The README and every page under docs/."""
    return [README, *sorted(DOCS.rglob("*.md"))]


def fenced_blocks(path: Path, language: str) -> list[tuple[int, str, str]]:
    """``(line number, marker, code)`` of each ```` ```language ```` block of ``path``; the
    marker is the last non-blank line before the fence (``""`` where it is not a comment)."""
    lines = path.read_text().splitlines()
    blocks, index = [], 0
    while index < len(lines):
        if lines[index].strip() == f"```{language}":
            end = next(i for i in range(index + 1, len(lines)) if lines[i].strip() == "```")
            before = [line.strip() for line in lines[:index] if line.strip()]
            marker = before[-1] if before and before[-1].startswith("<!--") else ""
            blocks.append((index + 1, marker, "\n".join(lines[index + 1 : end]) + "\n"))
            index = end
        index += 1
    return blocks


def python_blocks(marker: str) -> list:
    """The Python blocks marked ``marker``, as pytest parameters named ``FILE:LINE``."""
    return [
        pytest.param(code, id=f"{path.relative_to(ROOT)}:{line}")
        for path in markdown_files()
        for line, mark, code in fenced_blocks(path, "python")
        if mark == marker
    ]


# Generated reference pages ---------------------------------------------------------------------


def test_the_committed_reference_pages_are_those_the_code_generates(tmp_path):
    gen.write(tmp_path)
    committed = {path.name for path in (DOCS / "reference").glob("*.md")}
    assert committed == set(gen.PAGES), "docs/reference/ holds pages the generator does not write"
    stale = [
        name
        for name in gen.PAGES
        if (tmp_path / name).read_text() != (DOCS / "reference" / name).read_text()
    ]
    assert not stale, f"stale pages {stale}: run `python docs/gen_reference.py` and commit them"


def test_the_pages_say_what_the_code_has():
    """Spot checks of the generated text against independent facts of the code."""
    config = (DOCS / "reference" / "config.md").read_text()
    for field in dataclasses.fields(TrainConfig):
        assert f"| `{field.name}` | `--{field.name.replace('_', '-')}` |" in config
    assert "| `actor_lr` | `--actor-lr` | `float` or `None` | `None` | yes |" in config
    cli = (DOCS / "reference" / "cli.md").read_text()
    assert "## td3-jax sweep" in cli and "--sweep-actor-lr" in cli and "--total-steps" in cli
    errors = (DOCS / "reference" / "errors.md").read_text()
    assert "| `NonFiniteError` | `TrainingStopped` | 3 |" in errors


@dataclasses.dataclass(frozen=True)
class ConfigWithANewField(TrainConfig):
    """A setting added without its docstring."""

    documented: int = 1
    """A documented field."""
    bare_new_setting: int = 0


@dataclasses.dataclass(frozen=True)
class CommandWithABareFlag:
    """A subcommand whose second flag has no help text."""

    run: Path = Path(".")
    """Run directory."""
    episodes: int = 3


def test_a_field_without_a_docstring_stops_the_generator():
    with pytest.raises(gen.MissingDocstringError, match="bare_new_setting") as raised:
        gen.field_docstrings(ConfigWithANewField)
    assert "documented" not in str(raised.value).replace("bare_new", "")
    docs = gen.field_docstrings(TrainConfig)
    assert docs["env"].startswith("Environment as SOURCE/NAME")


def test_a_flag_without_a_docstring_fails_the_generator_with_exit_code_1(tmp_path, monkeypatch):
    monkeypatch.setattr(gen, "command_classes", lambda: {"eval": CommandWithABareFlag})
    err = io.StringIO()
    with contextlib.redirect_stderr(err):
        code = gen.main(["--out", str(tmp_path)])
    assert code == 1
    assert "CommandWithABareFlag" in err.getvalue() and "episodes" in err.getvalue()
    assert "run," not in err.getvalue()  # (the documented flag is not named)


def test_a_subclass_field_takes_the_subclass_docstring():
    from td3_jax.cli.commands import TrainCommand

    assert gen.field_docstrings(TrainCommand)["hidden_sizes"].startswith("Hidden widths")
    assert gen.field_docstrings(TrainCommand)["out"].startswith("Run directory")


# Python blocks -----------------------------------------------------------------------------


def test_every_python_block_is_marked_runnable():
    """Each Python block says whether the fast or the slow test runs it, or includes an
    examples/ file (which has its own tests)."""
    unmarked = [
        f"{path.relative_to(ROOT)}:{line}"
        for path in markdown_files()
        for line, marker, code in fenced_blocks(path, "python")
        if marker not in (FAST, SLOW) and not re.fullmatch(r'--8<-- "examples/\w+\.py"\n', code)
    ]
    assert not unmarked, f"Python blocks without {FAST} or {SLOW}: {unmarked}"
    assert len(python_blocks(FAST)) >= 4 and len(python_blocks(SLOW)) >= 4


def run_block(code: str, folder: Path, monkeypatch) -> None:
    """Runs ``code`` as a script of its own in ``folder`` (files it writes land there)."""
    monkeypatch.chdir(folder)
    exec(compile(code, "<docs block>", "exec"), {"__name__": "__docs__"})


@pytest.mark.parametrize("code", python_blocks(FAST))
def test_a_fast_python_block_runs_as_pasted(code, tmp_path, monkeypatch):
    run_block(code, tmp_path, monkeypatch)


@pytest.mark.slow
@pytest.mark.parametrize("code", python_blocks(SLOW))
def test_a_slow_python_block_runs_as_pasted(code, tmp_path, monkeypatch):
    run_block(code, tmp_path, monkeypatch)


# Commands ----------------------------------------------------------------------------------


def command_flags() -> dict[str, set[str]]:
    """Each subcommand's flags: its fields' (and ``--no-`` for booleans), with ``--help``."""
    flags = {}
    for name, cls in gen.command_classes().items():
        fields = dataclasses.fields(cls)
        names = {f"--{field.name.replace('_', '-')}" for field in fields}
        names |= {
            f"--no-{field.name.replace('_', '-')}" for field in fields if field.type == "bool"
        }
        flags[name] = names | {"--help", "-h"}
    return flags


def td3_jax_commands(text: str) -> list[list[str]]:
    """The ``td3-jax`` commands of a bash block: lines joined at trailing backslashes, split
    at ``&&``, ``;`` and ``|``, comments and the bracketed optional parts left out."""
    joined = text.replace("\\\n", " ")
    commands = []
    for line in joined.splitlines():
        for part in re.split(r"&&|;|\|", line):
            words = shlex.split(part, comments=True)
            at = next((i for i, w in enumerate(words) if w.endswith("td3-jax")), None)
            if at is not None and len(words) > at + 1:
                commands.append(words[at + 1 :])
    return commands


def test_every_command_in_the_docs_uses_flags_the_command_has():
    known = command_flags()
    wrong, seen = [], 0
    for path in markdown_files():
        for line, _, code in fenced_blocks(path, "bash"):
            for words in td3_jax_commands(code):
                if words[0] in ("--help", "--version"):
                    continue
                seen += 1
                where = f"{path.relative_to(ROOT)}:{line}"
                if words[0] not in known:
                    wrong.append(f"{where}: no subcommand {words[0]!r}")
                    continue
                flags = {w.split("=")[0] for w in words[1:] if re.match(r"--?[A-Za-z]", w)}
                wrong += [f"{where}: td3-jax {words[0]} {f}" for f in flags - known[words[0]]]
    assert seen > 30
    assert not wrong, "flags the commands do not have:\n" + "\n".join(wrong)


def test_the_check_catches_a_flag_that_does_not_exist():
    """The command check reads flags as the test above does: a mistyped one is found."""
    commands = td3_jax_commands("td3-jax train --totl-steps 10 \\\n  --out x  # note\n")
    assert commands == [["train", "--totl-steps", "10", "--out", "x"]]
    assert "--totl-steps" not in command_flags()["train"]
    assert {"--total-steps", "--no-normalize-obs", "--sweep-tau"} <= command_flags()["sweep"]


# The algorithm page's tests ------------------------------------------------------------------


def test_every_test_named_in_the_docs_exists():
    named = {
        (file, test)
        for path in markdown_files()
        for file, test in re.findall(r"`(tests/[\w/]+\.py)::(test_\w+)`", path.read_text())
    }
    assert len(named) > 40
    missing = [
        f"{file}::{test}"
        for file, test in sorted(named)
        if not (ROOT / file).is_file() or f"def {test}(" not in (ROOT / file).read_text()
    ]
    assert not missing, f"tests named in the docs that do not exist: {missing}"


# The README ----------------------------------------------------------------------------------


def test_the_readme_is_short_and_starts_with_its_two_commands():
    text = README.read_text()
    assert len(text.splitlines()) <= 200
    setup = "python3 -m venv .venv && .venv/bin/pip install -q -e"
    main_job = f"{setup} . && .venv/bin/td3-jax train --out runs/pendulum"
    tests = f"{setup} '.[dev]' && .venv/bin/python -m pytest -q -n auto --dist loadfile " + \
        '-m "not heavy"'  # fmt: skip
    blocks = [code.strip() for _, _, code in fenced_blocks(README, "bash")]
    assert blocks[:2] == [main_job, tests]
    assert tests.split(" && ")[-1] in (ROOT / ".ci" / "run").read_text()  # CI runs it


def test_the_readme_links_to_files_that_exist():
    links = re.findall(
        r"\]\(((?:docs/|examples/)[^)#]+|[A-Z]+\.md)(?:#[^)]*)?\)", README.read_text()
    )
    assert len(links) > 20
    missing = sorted({link for link in links if not (ROOT / link).exists()})
    assert not missing, f"README links to missing files: {missing}"


# metrics.jsonl -----------------------------------------------------------------------------


@pytest.mark.runs
def test_the_metrics_page_names_every_field_of_a_runs_records(tmp_path):
    """A run of two seeds with reward scaling and the evaluation inside the chunk writes
    records whose every field the page describes; only the divergence field is not seen."""
    flags = [*TINY_FLAGS, "--seeds", "2", "--return-bound", "5", "--eval-in-chunk"]
    code, _, err = main(["train", *flags, "--out", str(tmp_path / "run"), "--quiet"])
    assert code == 0, err
    records = read_records(tmp_path / "run")
    seen = set().union(*(record.keys() for record in records))
    documented = {name for name, _, _ in gen.METRICS}
    assert seen <= documented, f"fields the metrics page does not describe: {seen - documented}"
    assert documented - seen == {"diverged_members"}
    described = dict((name, what) for name, _, what in gen.METRICS)["per_member"]
    for key in records[-1]["per_member"][0]:
        assert f"`{key}`" in described or key.startswith("eval_return_"), key


# Pages that restate the code -----------------------------------------------------------------


def test_the_run_directory_page_names_every_setting_a_resume_may_change():
    """The resume paragraph lists exactly the settings ``rundir.SAFE_ON_RESUME`` lets change
    (the W&B ones as ``--wandb*``)."""
    from td3_jax.config.schema import WANDB_SETTINGS, flag
    from td3_jax.runner.rundir import SAFE_ON_RESUME

    page = (DOCS / "concepts" / "run-directory.md").read_text()
    paragraph = page.split("**What may change on resume.**")[1].split("\n\n")[0]
    listed = re.sub(r"\([^)]*\)", "", paragraph.split(";")[0])  # (the list, asides left out)
    assert "the `--wandb*` flags" in listed
    named = set(re.findall(r"`(--[a-z-]+)`", listed))
    assert named == {flag(name) for name in set(SAFE_ON_RESUME) - set(WANDB_SETTINGS)}


def test_the_export_page_imports_only_what_the_export_extra_installs():
    """The deployment block needs nothing beyond td3-jax and its export extra."""
    import tomllib

    project = tomllib.loads((ROOT / "pyproject.toml").read_text())["project"]
    requirements = [*project["dependencies"], *project["optional-dependencies"]["export"]]
    installed = {re.split(r"[<>=\[ ]", requirement)[0] for requirement in requirements}
    page = DOCS / "guides" / "export.md"
    (code,) = [code for _, marker, code in fenced_blocks(page, "python") if marker == SLOW]
    imported = set(re.findall(r"^(?:import|from) (\w+)", code, re.M))
    assert imported == {"numpy", "onnx", "td3_jax"}
    assert imported - {"td3_jax"} <= installed, (imported, installed)
