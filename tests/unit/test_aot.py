"""The kernels built ahead of time (hil.runtime.aot) give the Python kernels' bits, as numba's JIT
ones do, load without numba, and refuse operands they were not compiled for instead of misreading
them. Built here into a temporary directory, so this holds whether or not ``make`` built one."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from hil.runtime import prebuilt

ROOT = Path(__file__).resolve().parents[2]

# CI (HIL_REQUIRE_VCAN, set by .ci/run, which installs gcc) never skips
pytestmark = pytest.mark.skipif(
    shutil.which("cc") is None and shutil.which("gcc") is None and not os.environ.get("HIL_REQUIRE_VCAN"),
    reason="no C compiler to build the kernels ahead of time (.ci/run installs gcc)",
)


@pytest.fixture(scope="module")
def built(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    """Built by the command ``make`` runs, which says what it built."""
    d = tmp_path_factory.mktemp("kernels")
    res = _run([sys.executable, "-m", "hil.runtime.aot", "--dir", str(d)], _env(d))
    assert res.returncode == 0, res.stderr
    assert res.stdout.startswith(f"built {d}/hil_kernels_")
    assert sorted(p.suffix for p in d.iterdir()) == [".json", ".so"]
    yield d


def _env(kernels_dir: Path, **extra: str) -> dict[str, str]:
    env = {k: v for k, v in os.environ.items() if k != "HIL_JIT"}
    return dict(env, HIL_KERNELS_DIR=str(kernels_dir), PYTHONPATH=str(ROOT), **extra)


def _run(args: list[str], env: dict[str, str]) -> subprocess.CompletedProcess[str]:
    return subprocess.run(args, env=env, capture_output=True, text=True, timeout=600, cwd=ROOT)


def test_they_load_without_numba_and_are_put_in_place(built: Path) -> None:
    code = (
        "import sys\n"
        "from hil.runtime import jit\n"
        "from hil.nav import strapdown\n"
        "print(jit.enable()); print(jit.source()); print('numba' in sys.modules)\n"
        "print(strapdown._step is jit.compiled_kernel('_step'))\n"
        "from hil.nav import kernels; print(kernels.compiled, kernels.ahead_of_time)\n"
    )
    res = _run([sys.executable, "-c", code], _env(built))
    assert res.returncode == 0, res.stderr
    state, source, numba_loaded, in_place, counted = res.stdout.split("\n")[:5]
    assert state == "compiled"
    assert source.startswith(f"ahead of time ({built}/hil_kernels_")
    assert (numba_loaded, in_place) == ("False", "True")
    assert counted == "True True"  # the fusion's status: kernels.compiled, kernels.ahead_of_time
    res = _run([sys.executable, "-c", code], _env(built, HIL_JIT="numba"))
    assert res.returncode == 0, res.stderr
    assert res.stdout.split("\n")[1:3] == ["numba's cache", "True"]
    assert res.stdout.split("\n")[4] == "True False"


def test_every_kernel_gives_the_python_bits(built: Path) -> None:
    """The JIT kernels' tests (random operands, each kernel against its Python one and einsum's
    orders), run with these in place. Not ``hil bench jit``'s test, which "compiled" also
    matched: the bench leaves ``HIL_*`` out of its children, so with these in ``HIL_KERNELS_DIR``
    alone (none built in the package's ``__pycache__``) it failed, a kernel's bits unchecked."""
    runner = [sys.executable, "-m", "pytest", "-q", "-p", "no:cacheprovider"]
    res = _run([*runner, "tests/unit/test_jit.py", "-k", "compiled and not bench"], _env(built))
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-2000:]
    assert " passed" in res.stdout and "failed" not in res.stdout


def test_a_recording_made_with_numbas_kernels_reruns_bit_for_bit_with_these(
    built: Path, tmp_path: Path
) -> None:
    rec = tmp_path / "s.mcap"
    sim = _run(
        [
            sys.executable,
            "-m",
            "hil.cli",
            "sim",
            "--scenario",
            "uav_survey",
            "--duration",
            "8",
            "--record",
            str(rec),
        ],
        _env(built, HIL_JIT="numba"),
    )
    assert sim.returncode == 0, sim.stderr
    res = _run(
        [sys.executable, "-m", "hil.cli", "rerun", str(rec), "--core", "fusion", "--verify"], _env(built)
    )
    assert res.returncode == 0, res.stdout + res.stderr
    assert "bit-identical" in res.stdout


def test_an_operand_they_were_not_compiled_for_is_refused_not_misread(built: Path) -> None:
    loaded = prebuilt.load([built])
    assert loaded is not None
    kernels, _path = loaded
    expm = kernels["expm"]  # compiled for a C-ordered float64 matrix
    m = np.random.default_rng(3).normal(size=(4, 4)) * 0.1
    want = expm(m.copy())
    for bad in (m.astype(np.float32), np.asfortranarray(m)[:, :], np.ones((4, 8))[:, ::2], [[1.0]], m[0]):
        with pytest.raises(TypeError, match="expm: operand 0 is not the array"):
            expm(bad)
    readonly = m.copy()
    readonly.flags.writeable = False
    with pytest.raises(TypeError):
        expm(readonly)
    assert expm(m.copy()).tobytes() == want.tobytes()


def _copy(built: Path, to: Path) -> tuple[Path, Path]:
    """The module and its operands file copied into a directory of their own (a module file loaded
    once is never written over: the process that loaded it has it mapped)."""
    to.mkdir(parents=True, exist_ok=True)
    for f in built.iterdir():
        shutil.copy(f, to / f.name)
    return next(to.glob("hil_kernels_*.so")), next(to.glob("hil_kernels_*.json"))


def _operands(spec: Path, operands: object) -> None:
    """The operands file with these operands, the module's size and sha256 as built."""
    spec.write_text(json.dumps(dict(json.loads(spec.read_text()), operands=operands)))


def _warnings(err: str) -> list[str]:
    return [line for line in err.splitlines() if line.startswith("hil: warning: ")]


def test_a_module_for_other_sources_or_a_damaged_one_is_not_used(
    built: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    assert prebuilt.load([tmp_path]) is None  # none built there
    assert capsys.readouterr().err == ""  # and nothing to say
    stale = tmp_path / "stale"
    stale.mkdir()
    for f in built.iterdir():  # a module of other sources: another digest in its name
        shutil.copy(f, stale / f.name.replace("hil_kernels_", "hil_kernels_0"))
    assert prebuilt.load([stale]) is None
    damaged = tmp_path / "damaged"
    so, spec = _copy(built, damaged)
    so.write_bytes(b"not an ELF file")  # recorded as built: the loader's own refusal
    spec.write_text(
        json.dumps(dict(json.loads(spec.read_text()), module=prebuilt.module_record(so.read_bytes())))
    )
    capsys.readouterr()
    assert prebuilt.load([damaged]) is None
    assert "does not load" in capsys.readouterr().err
    # an operands file that names a kernel the module lacks, or is not the builder's shape
    for i, operands in enumerate(({"no_such_kernel": []}, {"expm": 3}, None)):
        _so, spec = _copy(built, tmp_path / f"operands{i}")
        if operands is None:
            spec.write_text("[not json")
        else:
            _operands(spec, operands)
        assert prebuilt.load([spec.parent]) is None, operands
        assert "does not load" in capsys.readouterr().err


def test_a_module_for_other_sources_is_named_with_what_to_run(
    built: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A kernel edited since the build (another digest): numba's kernels, compiled for ~12 s,
    and one line saying which module was found, why it is not used and what builds it (there
    was none: the compile went unexplained)."""
    for f in built.iterdir():
        shutil.copy(f, tmp_path / f.name.replace("hil_kernels_", "hil_kernels_0"))
    assert prebuilt.load([tmp_path]) is None
    (line,) = _warnings(capsys.readouterr().err)
    assert f"{tmp_path}/hil_kernels_0" in line and "was built for other sources" in line
    assert (
        "numba's kernels are used" in line and "make kernels" in line and "python -m hil.runtime.aot" in line
    )


def test_a_named_directory_that_is_none_is_said_and_an_absent_default_is_not(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """``HIL_KERNELS_DIR`` missing, or a file: one line each (it was silence, and numba's ~12 s
    compile); the package's ``__pycache__`` or the user's cache missing is a checkout where
    nothing was built, which says nothing."""
    defaults = [tmp_path / "no_pycache", tmp_path / "no_cache"]

    def directories(env: dict[str, str] | None = None) -> list[Path]:
        assert env is not None
        return ([Path(env["HIL_KERNELS_DIR"])] if env.get("HIL_KERNELS_DIR") else []) + defaults

    monkeypatch.setattr(prebuilt, "directories", directories)
    assert prebuilt.load(env={}) is None
    assert capsys.readouterr().err == ""
    afile = tmp_path / "afile"
    afile.write_text("")
    for named, why in ((tmp_path / "nope", "does not exist"), (afile, "is not a directory")):
        assert prebuilt.load(env={"HIL_KERNELS_DIR": str(named)}) is None
        (line,) = _warnings(capsys.readouterr().err)
        assert line.startswith(f"hil: warning: HIL_KERNELS_DIR={named} {why}: numba's kernels are used")
        assert "make kernels" in line


def test_a_directory_that_may_not_be_searched_is_said_not_raised(
    built: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """Its module's ``is_file`` raised PermissionError out of ``load`` (a traceback from ``hil
    rerun --one-process``, a worker gone without a word otherwise): now one line, numba's kernels,
    and the next directory still looked in."""
    closed = tmp_path / "closed"
    closed.mkdir()
    is_file = Path.is_file

    def denied(self: Path) -> bool:
        if self.parent == closed:
            raise PermissionError(13, "Permission denied", str(self))
        return is_file(self)

    monkeypatch.setattr(Path, "is_file", denied)
    assert prebuilt.load([closed]) is None
    (line,) = _warnings(capsys.readouterr().err)
    assert line.startswith(f"hil: warning: {closed} cannot be searched (Permission denied): numba's kernels")
    loaded = prebuilt.load([closed, built])  # a good module after it: used, and said so
    assert loaded is not None and loaded[1].parent == built
    (line,) = _warnings(capsys.readouterr().err)
    assert line.endswith(f"the kernels built ahead of time in {loaded[1]} are used")


def _no_dac(d: Path) -> list[str]:
    """``d`` made mode 000, and a command prefix under which it cannot be read: none for a user,
    setpriv dropping root's file-access capabilities for root (skipped where it cannot)."""
    d.chmod(0)
    if os.geteuid() != 0:
        return []
    caps = "-dac_override,-dac_read_search"
    prefix = ["setpriv", f"--bounding-set={caps}", f"--inh-caps={caps}"]
    dropped = shutil.which("setpriv") is not None and subprocess.run([*prefix, "true"]).returncode == 0
    if not dropped or subprocess.run([*prefix, "ls", str(d)], capture_output=True).returncode == 0:
        d.chmod(0o700)
        pytest.skip("root, and no setpriv to drop the capability to read a mode-000 directory")
    return prefix


def test_an_unreadable_kernels_dir_reruns_with_numbas_kernels_and_says_so(tmp_path: Path) -> None:
    """The QA reproduction: ``HIL_KERNELS_DIR`` a mode-000 directory, ``hil rerun --verify`` with
    the fusion in its worker (it died: "Broken pipe") and in one process (a PermissionError)."""
    rec = tmp_path / "s.mcap"
    sim = [sys.executable, "-m", "hil.cli", "sim", "--scenario", "uav_survey", "--duration", "4"]
    res = _run([*sim, "--record", str(rec), "--quiet"], _env(tmp_path, HIL_JIT="numba"))
    assert res.returncode == 0, res.stderr
    closed = tmp_path / "closed"
    closed.mkdir()
    prefix = _no_dac(closed)
    try:
        for how in ([], ["--one-process"]):
            rerun = [sys.executable, "-m", "hil.cli", "rerun", str(rec), "--core", "fusion", "--verify", *how]
            res = _run([*prefix, *rerun], _env(closed))
            assert res.returncode == 0, res.stdout + res.stderr
            assert "bit-identical" in res.stdout
            warned = _warnings(res.stderr)
            assert warned and all(
                line.startswith(f"hil: warning: HIL_KERNELS_DIR={closed} cannot be searched")
                for line in warned
            ), res.stderr
    finally:
        closed.chmod(0o700)


def _load_in_a_process(d: Path) -> subprocess.CompletedProcess[str]:
    """``prebuilt.load`` of ``d`` in a process of its own: one that maps a damaged module may die."""
    code = f"from pathlib import Path\nfrom hil.runtime import prebuilt\nprint(prebuilt.load([Path({str(d)!r})]))"
    return _run([sys.executable, "-c", code], _env(d))


def test_a_module_cut_short_or_written_over_is_refused_before_it_is_mapped(
    built: Path, tmp_path: Path
) -> None:
    """Its first 1000 bytes beside its operands file killed the process (SIGBUS, exit 135, no
    word); the builder records the module's size and sha256, checked before it is loaded."""
    so, _spec = _copy(built, tmp_path / "short")
    so.write_bytes(so.read_bytes()[:1000])
    res = _load_in_a_process(so.parent)
    assert res.returncode == 0, res
    assert res.stdout == "None\n"
    (line,) = _warnings(res.stderr)
    assert line.startswith(f"hil: warning: {so} is not used: it is 1000 bytes, not the ")
    assert "cut short" in line and "numba's kernels are used" in line and "make kernels" in line
    so, _spec = _copy(built, tmp_path / "over")
    data = bytearray(so.read_bytes())
    data[len(data) // 2 :] = bytes(len(data) - len(data) // 2)  # the same size, its second half zeros
    so.write_bytes(bytes(data))
    res = _load_in_a_process(so.parent)
    assert (res.returncode, res.stdout) == (0, "None\n"), res
    (line,) = _warnings(res.stderr)
    assert line.startswith(f"hil: warning: {so} is not used: its sha256 is not that of the module built")


def test_a_module_without_its_size_and_sha256_is_treated_as_stale(
    built: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """An older builder's operands file (the operands alone), or none at all: not loaded, said."""
    so, spec = _copy(built, tmp_path / "older")
    spec.write_text(json.dumps(json.loads(spec.read_text())["operands"]))
    assert prebuilt.load([so.parent]) is None
    (line,) = _warnings(capsys.readouterr().err)
    assert line.startswith(f"hil: warning: {so} is not used: {spec.name} records no size and sha256 of it")
    assert "make kernels" in line
    so, spec = _copy(built, tmp_path / "alone")
    spec.unlink()
    assert prebuilt.load([so.parent]) is None
    (line,) = _warnings(capsys.readouterr().err)
    assert line.startswith(f"hil: warning: {so} is not used: it has no operands file")


def test_the_builder_refuses_a_kernels_dir_it_cannot_write(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]
) -> None:
    """``HIL_KERNELS_DIR`` a file: the builder wrote into the package's ``__pycache__`` without a
    word, where another environment naming that directory never looks. Refused in one line, before
    anything is compiled."""
    from hil.runtime import aot

    afile = tmp_path / "afile"
    afile.write_text("")
    monkeypatch.setenv("HIL_KERNELS_DIR", str(afile))
    monkeypatch.setattr(aot, "_writable", lambda dirs: pytest.fail(f"would write to the first of {dirs}"))
    assert aot.main([]) == 1
    err = capsys.readouterr().err
    assert err.count("\n") == 1
    assert f"HIL_KERNELS_DIR={afile} is not a directory: set it to a directory this user may write" in err


def test_a_module_whose_operands_file_names_fewer_kernels_is_not_put_in_place(
    built: Path, tmp_path: Path
) -> None:
    _so, spec = _copy(built, tmp_path)
    _operands(spec, {"_step": json.loads(spec.read_text())["operands"]["_step"]})
    code = "from hil.runtime import jit; print(jit.enable()); print(jit.source())"
    res = _run([sys.executable, "-c", code], _env(tmp_path))
    assert res.returncode == 0, res.stderr
    assert res.stdout.split("\n")[:2] == ["compiled", "numba's cache"]
    assert "lacks _advance, _carry, _corrected_run" in res.stderr
