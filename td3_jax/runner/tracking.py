"""Weights & Biases for a run (``--wandb``): a mirror of what the run directory records.

Each evaluation record of ``metrics.jsonl`` is logged with the same keys and numbers (nested
ones, a population's ``per_member``, under ``per_member/0/eval_return_mean``, ...; text and
null are left out, as TensorBoard leaves them), plotted against ``env_steps`` (evaluation
returns against the env steps of the policy evaluated, as in TensorBoard and curve.png);
``config.json`` is the W&B run's config and ``curve.png`` is logged as an image when the run
ends. W&B's files go to ``OUT/wandb/``, which also holds the W&B run's id, so ``--resume``
continues the same W&B run, and the env steps of the last record sent to each W&B run: a
resume rewrites the records past its checkpoint, and those that W&B run has already are not
sent again (nor written to an offline part, which is synced into it), so that W&B's history
holds one point of each (a W&B run cannot take points back, as TensorBoard's purge does).
The resume is exact, so they are the same numbers, unless it changes how they are computed
(``--eval-envs``, ``--matmuls``, another GPU model): W&B then keeps the first part's.
``wandb`` is imported only when a run asks for it: importing this module changes no
process-wide state.

metrics.jsonl is written before W&B is told: a W&B failure during a run is one warning, after
which the run goes on without W&B and loses no record. W&B's own banners (its version, the
offline notice, the history and summary at the end) are not printed: td3-jax says in one line
where the W&B run is; W&B's warnings and errors still show.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import math
import os
import re
import secrets
import shlex
import string
import sys
from collections.abc import Callable
from contextlib import redirect_stderr, redirect_stdout
from pathlib import Path
from types import ModuleType
from typing import Any

from td3_jax.common.errors import WandbError
from td3_jax.config.schema import TrainConfig
from td3_jax.runner.logger import evaluated_steps, is_return, write_atomically

__all__ = [
    "ID_FILE",
    "SENT_FILE",
    "WANDB_DIR",
    "Tracker",
    "WandbError",
    "check_ready",
    "import_wandb",
    "init_arguments",
    "mode",
    "numbers",
    "start",
]

#: The folder of the run directory that holds W&B's files (W&B's own name for it).
WANDB_DIR = "wandb"
#: The file, in :data:`WANDB_DIR`, holding the id of the run directory's W&B run.
ID_FILE = "td3-jax-run-id"
#: The file, in :data:`WANDB_DIR`, holding the env steps of the last record sent to each W&B
#: run (:func:`destination`: entity, project and run id), as a JSON object.
SENT_FILE = "td3-jax-sent"
_MISSING = "--wandb needs the wandb package: pip install 'td3-jax[wandb]'"
_NO_LOGIN = (
    "--wandb: not logged in to Weights & Biases (no API key); run `wandb login` (or set "
    "WANDB_API_KEY), or use --wandb-mode offline and upload the run later with `wandb sync`"
)


def import_wandb() -> ModuleType:
    """The ``wandb`` module; :class:`WandbError` naming the extra to install where it is not."""
    try:
        import wandb
    except ImportError:
        raise WandbError(_MISSING) from None
    return wandb


def mode(cfg: TrainConfig) -> str:
    """The W&B mode of a run: ``--wandb-mode``, else ``$WANDB_MODE``, else online (with W&B's
    own aliases: ``dryrun`` is offline, ``run`` online)."""
    chosen = cfg.wandb_mode or os.environ.get("WANDB_MODE") or "online"
    chosen = {"dryrun": "offline", "run": "online"}.get(chosen, chosen)
    if chosen not in ("online", "offline", "disabled", "shared"):
        raise WandbError(f"$WANDB_MODE is {chosen!r}; W&B's modes are online, offline, disabled "
                         "and shared (or give --wandb-mode online|offline)")  # fmt: skip
    return chosen


def check_ready(cfg: TrainConfig) -> None:
    """Raises :class:`WandbError` when ``--wandb`` cannot work here (no ``wandb`` package, or
    online mode without a login); does nothing without ``--wandb``. Reads no network."""
    if not cfg.wandb:
        return
    wandb = import_wandb()
    if mode(cfg) not in ("offline", "disabled") and not _logged_in(wandb):
        raise WandbError(_NO_LOGIN)


def _logged_in(wandb: ModuleType) -> bool:
    """Whether W&B finds credentials (an API key, an identity token), without prompting."""
    try:
        return bool(wandb.login(prompt=False, verify=False))
    except TypeError:  # a wandb without login(prompt=...): ask its API object instead
        return wandb.api.api_key is not None


def numbers(record: dict[str, Any] | list[Any], prefix: str = "") -> dict[str, int | float]:
    """The finite numbers of a metrics.jsonl record, keyed as in the record; those nested in
    dicts and lists under slash-joined keys (``per_member/0/eval_return_mean``). Text, booleans,
    null and non-finite values are left out."""
    found: dict[str, int | float] = {}
    items = record.items() if isinstance(record, dict) else enumerate(record)
    for key, value in items:
        name = f"{prefix}{key}"
        if isinstance(value, dict | list):
            found.update(numbers(value, name + "/"))
        elif isinstance(value, int | float) and not isinstance(value, bool):
            if math.isfinite(value):
                found[name] = value
    return found


def init_arguments(cfg: TrainConfig, out_dir: Path, run_id: str) -> dict[str, Any]:
    """The keyword arguments of ``wandb.init`` for the run in ``out_dir`` (W&B's files inside
    it; the run named after it unless ``--wandb-name`` is given; resumed where ``run_id``
    exists already)."""
    out_dir = Path(out_dir)
    arguments = dict(
        project=cfg.wandb_project,
        entity=cfg.wandb_entity,
        name=cfg.wandb_name or out_dir.resolve().name,
        id=run_id,
        resume="allow",
        dir=str(out_dir),
    )
    if cfg.wandb_mode is not None:  # else W&B reads $WANDB_MODE itself
        arguments["mode"] = cfg.wandb_mode
    return arguments


def _run_id(out_dir: Path, resume: bool) -> str:
    """The W&B run id of ``out_dir``: on resume the stored one (where there is one), else a new
    one, stored in ``OUT/wandb/td3-jax-run-id``."""
    path = Path(out_dir) / WANDB_DIR / ID_FILE
    if resume and path.is_file() and path.read_text().strip():
        return path.read_text().strip()
    alphabet = string.ascii_lowercase + string.digits
    run_id = "".join(secrets.choice(alphabet) for _ in range(8))
    path.parent.mkdir(exist_ok=True)
    write_atomically(path, run_id + "\n")
    return run_id


def destination(arguments: dict[str, Any]) -> str:
    """The W&B run that ``wandb.init(**arguments)`` sends records to, as one key: entity (else
    ``$WANDB_ENTITY``), project and run id. A resume may change ``--wandb-project`` and
    ``--wandb-entity``: the same id there is another W&B run, with none of the records sent
    before. The mode is not part of it: an offline part is synced into the same W&B run
    (``wandb sync``), so it must not hold the records the W&B run has already."""
    entity = arguments.get("entity") or os.environ.get("WANDB_ENTITY") or ""
    return f"{entity}|{arguments['project'] or ''}|{arguments['id']}"


def _sent_notes(path: Path) -> dict[str, int]:
    """:data:`SENT_FILE`'s notes: the env steps of the last record sent to each
    :func:`destination` from this run directory (none where the file is missing or not of its
    form)."""
    try:
        notes = json.loads(path.read_text())
        return {str(to): int(steps) for to, steps in notes.items()}
    except (OSError, ValueError, AttributeError, TypeError):  # none yet, or not its form
        return {}


@dataclasses.dataclass
class Tracker:
    """A W&B run that mirrors one training call's records, config and curve.

    Its methods never raise: a W&B failure becomes one warning and W&B is left alone for the
    rest of the run (the records are in metrics.jsonl already).
    """

    run: Any
    """The ``wandb`` run."""
    image: Callable[[str], Any]
    """``wandb.Image``."""
    env_steps: int | None = None
    """The env steps of the last record logged."""
    failed: bool = False
    """Whether a W&B call failed (nothing more is sent)."""
    sent_through: int | None = None
    """The env steps of the last record W&B has from before a resume: records up to there are
    not sent again."""
    sent_file: tuple[Path, str] | None = None
    """Where to note each record sent (:data:`SENT_FILE`), and where it went
    (:func:`destination`)."""

    def log(self, record: dict[str, Any]) -> None:
        """Logs a metrics.jsonl record's numbers (:func:`numbers`) at its env steps, its
        evaluation returns at those of the policy evaluated (as TensorBoard places them;
        :func:`td3_jax.runner.logger.evaluated_steps`); a record at env steps W&B has already (from
        before a resume) is not logged a second time."""
        steps = int(record["env_steps"])
        if self.sent_through is not None and steps <= self.sent_through:
            self.env_steps = steps
            return
        values, evaluated = numbers(record), evaluated_steps(record)
        if evaluated != values["env_steps"]:  # an evaluation inside the chunk: logged apart,
            # first (its env steps are the earlier: W&B's env_steps then never goes back, and
            # the run's summary keeps the record's)
            returns = {k: values.pop(k) for k in list(values) if is_return(k)}
            self._guard(lambda: self.run.log({**returns, "env_steps": evaluated}))
        self._guard(lambda: self.run.log(values))
        self.env_steps = steps
        self._note_sent(steps)

    def _note_sent(self, steps: int) -> None:
        """Notes in :data:`SENT_FILE` that W&B was sent the record of ``steps`` (unless a W&B
        call failed; a note the disk refuses is left out: a resume then sends again what W&B
        has, which is all that a missing note costs)."""
        if self.sent_file is None or self.failed:
            return
        path, to = self.sent_file
        with contextlib.suppress(OSError):
            write_atomically(path, json.dumps({**_sent_notes(path), to: steps}) + "\n")

    def set_config(self, config: dict[str, Any]) -> None:
        """Makes ``config`` (config.json's contents) the W&B run's config."""
        self._guard(lambda: self.run.config.update(config, allow_val_change=True))

    def finish(self, curve: Path | None = None) -> None:
        """Logs ``curve`` (curve.png, where drawn) as an image, then ends the W&B run."""
        if curve is not None:
            at = {} if self.env_steps is None else {"env_steps": self.env_steps}
            self._guard(lambda: self.run.log({"curve": self.image(str(curve)), **at}))
        self._guard(self.run.finish)

    def _guard(self, action: Callable[[], Any]) -> None:
        """Runs ``action`` unless an earlier one failed; a failure is one warning."""
        if self.failed:
            return
        try:
            action()
        except Exception as err:  # the network, W&B's service process, ...
            self.failed = True
            print(f"td3-jax: warning: Weights & Biases failed ({type(err).__name__}: {err}); "
                  "the run goes on without it (metrics.jsonl keeps every record)",
                  file=sys.stderr)  # fmt: skip


def start(cfg: TrainConfig, out_dir: Path, *, resume: bool, enabled: bool = True) -> Tracker | None:
    """Starts the W&B run of ``out_dir`` (on ``resume``, continues the one stored there);
    ``None`` without ``--wandb`` or where ``enabled`` is false (a process that writes no logs).
    A W&B run that cannot start (no network, a refused login) is a :class:`WandbError`."""
    if not (cfg.wandb and enabled):
        return None
    wandb = import_wandb()
    run_id = _run_id(out_dir, resume)
    arguments = init_arguments(cfg, out_dir, run_id)
    try:
        run = wandb.init(**arguments, settings=wandb.Settings(**init_settings()))
        run.define_metric("env_steps")
        run.define_metric("*", step_metric="env_steps")
    except Exception as err:  # wandb.errors.CommError, AuthenticationError, UsageError, ...
        text = " ".join(_ANSI_CODES.sub("", str(err)).split()) or type(err).__name__
        _teardown_quietly(wandb)  # (its farewell lines would come after the run's error line)
        raise WandbError(
            f"--wandb: Weights & Biases could not start the run ({text}); check `wandb login` "
            "and the network, or use --wandb-mode offline"
        ) from None
    _say_where(run)
    to, notes = destination(arguments), Path(out_dir) / WANDB_DIR / SENT_FILE
    sent = _sent_notes(notes).get(to) if resume else None
    return Tracker(run, wandb.Image, sent_through=sent, sent_file=(notes, to))


#: Seconds ``wandb.init`` may take to reach W&B before the run stops with one line (W&B's own
#: default is 90 s, which a machine without network spent waiting); ``$WANDB_INIT_TIMEOUT``
#: sets it.
INIT_TIMEOUT_S = 30.0

#: Terminal colour codes, which W&B's error texts hold (``\x1b[1;34mwandb\x1b[0m: ...``).
_ANSI_CODES = re.compile(r"\x1b\[[0-9;]*[A-Za-z]")


def init_settings() -> dict[str, Any]:
    """``wandb.Settings``' arguments: W&B gets the numbers, not the console, and prints none
    of its banners (its warnings and errors stay); it waits :data:`INIT_TIMEOUT_S` to start
    unless ``$WANDB_INIT_TIMEOUT`` says how long."""
    settings: dict[str, Any] = {"console": "off", "silent": True}
    if not os.environ.get("WANDB_INIT_TIMEOUT"):
        settings["init_timeout"] = INIT_TIMEOUT_S
    return settings


def _say_where(run: Any) -> None:
    """Prints where the W&B run is, in the line W&B no longer prints: its page, or offline its
    folder and the command that uploads it; nothing for a disabled run (or a W&B that does not
    say)."""
    try:
        if run.disabled:
            return
        if run.offline:
            upload = f"wandb sync {shlex.quote(str(run.sync_dir))}"
            where = f"{run.sync_dir} (offline; upload it with: {upload})"
        else:
            where = run.url
    except AttributeError:  # a W&B without these properties
        return
    if where:
        print(f"W&B run: {where}", flush=True)


def _teardown_quietly(wandb: ModuleType) -> None:
    """Ends W&B's service after a run that did not start, now rather than at exit, so that its
    farewell (where its logs are) does not follow the run's error line: what it writes to
    ``sys.stdout``/``sys.stderr`` meanwhile is dropped, and nothing is left for exit."""
    with open(os.devnull, "w") as sink, redirect_stdout(sink), redirect_stderr(sink):
        try:
            wandb.teardown()
        except Exception:  # (nothing left to end, or a W&B without teardown)
            pass
