"""Packages skipped while a dependency imports: missing inside, importable again after, an
imported one untouched, and Playground made ready by td3-jax without running PyTorch."""

from __future__ import annotations

import os
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

PACKAGE = """
import os
with open(os.environ["LOADED_LOG"], "a") as log:
    log.write(__name__ + "\\n")
VALUE = 42
"""


def _fake_package(root: Path, name: str) -> None:
    (root / name).mkdir(parents=True)
    (root / name / "__init__.py").write_text(PACKAGE)


def _run(tmp_path: Path, code: str) -> tuple[list[str], list[str]]:
    """Runs ``code`` in a fresh Python that finds the fake packages under ``tmp_path/pkgs``;
    (its stdout's lines, the names of the packages whose code ran, in order)."""
    log = tmp_path / "loaded.log"
    env = {**os.environ, "LOADED_LOG": str(log),
           "PYTHONPATH": os.pathsep.join([str(tmp_path / "pkgs"), *sys.path])}  # fmt: skip
    proc = subprocess.run([sys.executable, "-c", textwrap.dedent(code)], env=env,
                          capture_output=True, text=True, timeout=300)  # fmt: skip
    assert proc.returncode == 0, proc.stderr
    loaded = log.read_text().split() if log.exists() else []
    return proc.stdout.splitlines(), loaded


@pytest.fixture
def packages(tmp_path: Path) -> Path:
    _fake_package(tmp_path / "pkgs", "fakepkg")
    return tmp_path


def test_a_skipped_package_is_missing_inside_and_imports_after(packages: Path) -> None:
    out, loaded = _run(
        packages,
        """
        from td3_jax.common.skipped_imports import skipping_unused_imports
        with skipping_unused_imports(["fakepkg"]) as skipped:
            print(skipped)
            try:
                import fakepkg
            except ImportError:
                print("ImportError")
        import fakepkg
        print(fakepkg.VALUE)
    """,
    )
    assert out == ["['fakepkg']", "ImportError", "42"]
    assert loaded == ["fakepkg"]  # (only the import after)


def test_an_imported_package_is_left_as_it_is(packages: Path) -> None:
    out, loaded = _run(
        packages,
        """
        import sys
        import fakepkg
        from td3_jax.common.skipped_imports import skipping_unused_imports
        with skipping_unused_imports(["fakepkg"]) as skipped:
            import fakepkg as inside
            print(skipped, inside is fakepkg)
        print(sys.modules["fakepkg"] is fakepkg)
    """,
    )
    assert out == ["[] True", "True"]
    assert loaded == ["fakepkg"]


def test_another_thread_imports_a_skipped_package_as_usual(packages: Path) -> None:
    """Only the thread inside the context is refused: another thread's import meanwhile gets
    the package, and then the context's thread finds it imported too."""
    out, loaded = _run(
        packages,
        """
        import threading
        from td3_jax.common.skipped_imports import skipping_unused_imports
        with skipping_unused_imports(["fakepkg"]) as skipped:
            got = []
            thread = threading.Thread(target=lambda: got.append(__import__("fakepkg").VALUE))
            thread.start()
            thread.join()
            import fakepkg
            print(skipped, got, fakepkg.VALUE)
        """,
    )
    assert out == ["['fakepkg'] [42] 42"]
    assert loaded == ["fakepkg"]


def test_a_submodule_of_a_skipped_package_is_refused_too(packages: Path) -> None:
    (packages / "pkgs" / "fakepkg" / "sub.py").write_text("ANSWER = 7\n")
    out, loaded = _run(
        packages,
        """
        import sys
        from td3_jax.common.skipped_imports import skipping_unused_imports
        with skipping_unused_imports(["fakepkg"]):
            try:
                import fakepkg.sub
            except ModuleNotFoundError as err:
                print(err.name, "fakepkg" in sys.modules)
        import fakepkg.sub
        print(fakepkg.sub.ANSWER)
        """,
    )
    assert out == ["fakepkg False", "7"]
    assert loaded == ["fakepkg"]


def test_a_package_another_thread_imported_meanwhile_is_not_refused(packages: Path) -> None:
    (packages / "pkgs" / "fakepkg" / "sub.py").write_text("ANSWER = 7\n")
    out, _ = _run(
        packages,
        """
        import threading
        from td3_jax.common.skipped_imports import skipping_unused_imports
        with skipping_unused_imports(["fakepkg"]):
            thread = threading.Thread(target=lambda: __import__("fakepkg"))
            thread.start()
            thread.join()
            import fakepkg.sub
            print(fakepkg.sub.ANSWER)
        """,
    )
    assert out == ["7"]


def test_playground_made_ready_by_td3_jax_does_not_run_torch(tmp_path: Path) -> None:
    """Playground imports ``torch`` wherever it is installed; through td3-jax (MJX and
    Playground's locomotion registry, as a robot run imports them) torch's code does not run,
    and ``import torch`` afterwards gives PyTorch as usual."""
    pytest.importorskip("mujoco_playground")
    _fake_package(tmp_path / "pkgs", "torch")
    out, loaded = _run(
        tmp_path,
        """
        import os, sys
        from td3_jax.common import upstream
        from td3_jax.envs import physics
        physics.import_mjx_quietly()
        registry = upstream.playground_locomotion()
        wrapper_torch = sys.modules["mujoco_playground._src.wrapper_torch"]
        print("T1JoystickFlatTerrain" in registry.ALL_ENVS, wrapper_torch.torch,
              os.path.exists(os.environ["LOADED_LOG"]))
        import torch
        print(torch.VALUE)
    """,
    )
    assert out == ["True None False", "42"]
    assert loaded == ["torch"]


def test_the_suite_is_imported_without_torch_too(tmp_path: Path) -> None:
    pytest.importorskip("mujoco_playground")
    _fake_package(tmp_path / "pkgs", "torch")
    out, loaded = _run(
        tmp_path,
        """
        from td3_jax.envs import playground
        print("CheetahRun" in playground.names())
    """,
    )
    assert out == ["True"]
    assert loaded == []


def test_a_playground_that_needs_a_skipped_package_is_said_as_such(monkeypatch) -> None:
    """Where Playground would need PyTorch to import at all, the skip is named (an upstream
    change), not taken for a missing Playground; another missing module stays itself."""
    import sys

    from td3_jax.common import upstream
    from td3_jax.common.errors import UpstreamChanged

    monkeypatch.delitem(sys.modules, "torch", raising=False)
    for missing, raised in (("torch.nn", UpstreamChanged), ("lxml", ModuleNotFoundError)):

        def failing(name: str, missing: str = missing) -> None:
            raise ModuleNotFoundError(f"No module named {missing!r}", name=missing)

        monkeypatch.setattr(upstream, "_private_module", failing)
        with pytest.raises(raised, match="torch.nn to be imported" if raised is UpstreamChanged
                           else "lxml"):  # fmt: skip
            upstream.playground_module(upstream.PLAYGROUND_LOCOMOTION)
