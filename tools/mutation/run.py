"""Mutation testing on demand (never in CI):
``.venv/bin/python tools/mutation/run.py [package ...]``.

Why a driver rather than a bare ``mutmut run``: mutmut names each mutant after its file's path
(with a leading ``src/`` stripped) and switches a mutant on only inside functions whose
``__module__`` has that name. Our folders install as ``busgate.codecs`` and ``busgate.gateway``
through setuptools' package-dir, so ``codecs/framing.py`` would be called ``codecs.framing``
while the tests import ``busgate.codecs.framing``, and no mutant would ever be switched on.
So this script copies the package into ``tools/mutation/work/<package>/src/busgate/<folder>``,
with tests/ and a pyproject.toml holding pytest's options and mutmut's, and runs mutmut there: the
copy is named ``busgate.<folder>`` and imported ahead of the editable install, and the folders
left uncopied still come from the editable install.

Why per package, and why a hypothesis profile: the whole suite takes minutes and opens ptys
and zenoh sessions, too slow for each of thousands of mutants. Each package gets the fast tests
that exercise it (mutmut then runs, for each mutant, only those of them that reached the
mutated function), and a conftest.py in the work folder loads a derandomized hypothesis
profile of 10 examples, so property tests are quick and every run finds the same examples.
The stateful decoder tests (tests/test_decoder_state_machines.py) are left out: at 50 machines
each they took half of the codecs' time per mutant, and the golden tests cover the same paths.
The bus owners get their own tests only (tests/test_bus_owner_edges.py, test_line_edges.py,
test_mutants_bus.py: ptys and the virtual bus played by the test, fake clocks, simulators
only where they answer late on purpose or with seconds to spare): the runner's tests
(test_bus_runner.py, test_can_runner.py) wait for simulators to answer within a 20-50 ms reply
margin, which a machine running two mutants at once sometimes misses, and a test that fails
for that counts a mutant as killed that it never caught.
The bases keep ``tests/test_base.py`` (without it, 178 of their mutants survive: the twist's
path, commands, claims), whose one running base (two simulated wheels on the virtual bus,
built once for the module) has failed for mutants it does not catch (docs/performance.md,
mutation scores): ``tests/test_mutants_base.py`` reaches the same code over a bus never
started, by plain calls, and a base mutant counted killed only by test_base.py may be luck.

Each run starts afresh and prints killed / total per package, with survivors and timeouts;
``results.json`` in the package's work folder keeps each mutant's status, and ``cd
tools/mutation/work/<package> && ../../../../.venv/bin/mutmut show NAME`` shows a mutant as a
diff. ``--again`` reruns only the mutants the last run did not kill, with the current tests,
and merges the result into the last run's (for checking new tests; the source must be
unchanged). tools/mutation/EQUIVALENT.md lists every survivor: the equivalent ones with the
reason, and the open ones (waiting for a killing test).
"""

from __future__ import annotations

import json
import re
import shutil
import subprocess
import sys
import time
import tomllib
from collections import Counter
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]  # this file is tools/mutation/run.py
WORK = ROOT / "tools" / "mutation" / "work"
MUTMUT = Path(sys.executable).parent / "mutmut"
CHILDREN = 2  # one package at a time, two mutants at once: the machine has two cores

CODEC_TESTS = [
    "tests/test_framing.py",
    "tests/test_ds_servo_codec.py",
    "tests/test_inspire_la_codec.py",
    "tests/test_zlac706_can_codec.py",
    "tests/test_zlac706_rs232_codec.py",
    "tests/test_ros2_codec.py",
    "tests/test_ds_servo_commands.py",
    "tests/test_inspire_la_commands.py",
    "tests/test_zlac706_commands.py",
    "tests/test_doctests.py",
    "tests/test_mutants_codecs.py",
    "tests/test_mutants_ros2.py",
]

#: The fast tests, by plain calls or over a bus never started, that reach every family's
#: driver beside its own tests: what each op's frames do, families, joints and their limits,
#: the safety rules, the e-stop's reset, reboots, telemetry, the idle bus's work.
DRIVER_NEIGHBOURS = [
    "tests/test_frame_effects.py",
    "tests/test_families.py",
    "tests/test_joints.py",
    "tests/test_joint_limits.py",
    "tests/test_safety_rules.py",
    "tests/test_estop_reset.py",
    "tests/test_reboots.py",
    "tests/test_telemetry.py",
    "tests/test_idle_work.py",
]

# package: (folder copied under src/busgate, files mutated (globs, relative to ROOT), tests)
PACKAGES: dict[str, tuple[str, list[str], list[str]]] = {
    "codecs": ("codecs", ["codecs/*"], CODEC_TESTS),
    "scheduler": (
        "gateway",
        ["gateway/scheduler/planner.py", "gateway/scheduler/tickers.py",
         "gateway/scheduler/streams.py", "gateway/scheduler/spacing.py"],
        ["tests/test_planner.py", "tests/test_joints.py", "tests/test_trajectory_ticks.py",
         "tests/test_mutants_scheduler.py", "tests/test_follow_spacing.py"],
    ),
    "bus": (
        "gateway",
        ["gateway/bus/serial_owner.py", "gateway/bus/can_owner.py", "gateway/bus/request.py",
         "gateway/bus/owner.py", "gateway/bus/tty_write.py"],
        ["tests/test_bus_owner_edges.py", "tests/test_line_edges.py", "tests/test_idle_work.py",
         "tests/test_socketcan_owner.py", "tests/test_mutants_bus.py"],
    ),
    "api": (
        "gateway",
        ["gateway/api/commands.py", "schemas/replies.py", "gateway/scheduler/authority.py"],
        ["tests/test_api.py", "tests/test_sharing_edges.py", "tests/test_error_codes.py",
         "tests/test_joint_limits.py", "tests/test_mutants_api.py"],
    ),
    "plays": (
        "gateway",
        ["gateway/scheduler/limiter.py", "gateway/scheduler/plays.py",
         "gateway/scheduler/trajectory_ticks.py"],
        ["tests/test_trajectory_ticks.py", "tests/test_trajectory_joints.py",
         "tests/test_joints.py", "tests/test_joint_limits.py", "tests/test_safety_rules.py",
         "tests/test_mutants_scheduler.py", "tests/test_mutants_base.py",
         "tests/test_mutants_plays.py"],
    ),
    "base": (
        "gateway",
        ["gateway/base/bases.py", "gateway/base/drive.py", "gateway/base/kinematics.py"],
        ["tests/test_base.py", "tests/test_base_kinematics.py", "tests/test_mutants_base.py"],
    ),
    "zlac706": (
        "gateway",
        ["gateway/drivers/zlac706.py", "gateway/drivers/zlac706_can.py",
         "gateway/drivers/zlac706_rs232.py", "gateway/drivers/zlac706_state.py"],
        ["tests/test_driver_zlac706.py", "tests/test_driver_setpoints.py",
         "tests/test_zlac706_commands.py", *DRIVER_NEIGHBOURS, "tests/test_mutants_base.py",
         "tests/test_mutants_zlac706.py"],
    ),
    "inspire_la": (
        "gateway",
        ["gateway/drivers/inspire_la.py", "gateway/drivers/inspire_la_frames.py"],
        ["tests/test_driver_inspire_la.py", "tests/test_driver_setpoints.py",
         "tests/test_inspire_la_commands.py", *DRIVER_NEIGHBOURS,
         "tests/test_mutants_inspire_la.py"],
    ),
    "ds_servo": (
        "gateway",
        ["gateway/drivers/ds_servo.py"],
        ["tests/test_driver_ds_servo.py", "tests/test_driver_setpoints.py",
         "tests/test_ds_servo_commands.py", *DRIVER_NEIGHBOURS, "tests/test_mutants_ds_servo.py"],
    ),
}

# mutmut's settings per package, over pyproject.toml's. The bus owners' tests catch a hanging
# mutant with a 5 s deadline; mutmut stops a mutant's run after (its tests' time + the
# constant) x the multiplier of wall-clock, about 9 s with the constant's 1 s, which pytest's
# start-up on a loaded machine plus that deadline can pass: a caught mutant was then counted
# a timeout.
MUTMUT_SETTINGS: dict[str, dict[str, object]] = {"bus": {"timeout_constant": 3.0}}

CONFTEST = '''"""Written by tools/mutation/run.py: quick, repeatable property tests, mutated."""
from hypothesis import settings

settings.register_profile("mutation", max_examples=10, derandomize=True, deadline=None)
settings.load_profile("mutation")
'''


def lay_out(package: str) -> Path:
    """A fresh work folder for ``package``: its source under src/busgate, tests, config."""
    folder, mutate, tests = PACKAGES[package]
    work = WORK / package
    shutil.rmtree(work, ignore_errors=True)
    ignore = shutil.ignore_patterns("__pycache__", ".hypothesis")
    shutil.copytree(ROOT / folder, work / "src" / "busgate" / folder, ignore=ignore)
    shutil.copytree(ROOT / "tests", work / "tests", ignore=ignore)
    (work / "conftest.py").write_text(CONFTEST)
    tool = tomllib.loads((ROOT / "pyproject.toml").read_text())["tool"]
    mutmut = {
        **tool.get("mutmut", {}),
        **MUTMUT_SETTINGS.get(package, {}),
        "source_paths": [f"src/busgate/{folder}"],
        "only_mutate": [f"src/busgate/{glob}" for glob in mutate],
        "pytest_add_cli_args_test_selection": [t for t in tests if (ROOT / t).exists()],
        "also_copy": ["conftest.py"],
    }
    lines = ["[tool.pytest.ini_options]"]
    # JSON's strings, numbers, booleans and lists of them are TOML too.
    lines += [f"{k} = {json.dumps(v)}" for k, v in tool["pytest"]["ini_options"].items()]
    lines += ["", "[tool.mutmut]"] + [f"{k} = {json.dumps(v)}" for k, v in mutmut.items()]
    (work / "pyproject.toml").write_text("\n".join(lines) + "\n")
    return work


def mutmut(work: Path, *args: str) -> str:
    done = subprocess.run([MUTMUT, *args], cwd=work, capture_output=True, text=True)
    with (work / "mutmut.log").open("a") as log:
        log.write(done.stdout + done.stderr)
    return done.stdout


def statuses(work: Path) -> dict[str, str]:
    listed = mutmut(work, "results", "--all", "true")
    return dict(re.findall(r"^\s+(\S+): (.+)$", listed, re.MULTILINE))


def run(package: str, again: bool) -> Counter:
    results_file = WORK / package / "results.json"
    if again and not results_file.exists():
        sys.exit(f"{package}: no finished run to go --again from ({results_file} is missing)")
    previous = json.loads(results_file.read_text()) if again else {}
    retry = sorted(name for name, status in previous.items() if status != "killed")
    work = lay_out(package)
    if not again:
        mutmut(work, "run", "--max-children", str(CHILDREN))
        results = statuses(work)
    elif retry:
        mutmut(work, "run", "--max-children", str(CHILDREN), *retry)
        results = {**previous, **{k: v for k, v in statuses(work).items() if k in retry}}
    else:
        results = previous
    if not results or "not checked" in results.values():
        if again:  # lay_out cleared the work folder: keep the last run's results for a retry
            results_file.write_text(json.dumps(previous, indent=1, ensure_ascii=False) + "\n")
        sys.exit(f"{package}: mutmut did not finish, see {work / 'mutmut.log'}")
    results_file.write_text(json.dumps(results, indent=1, ensure_ascii=False) + "\n")
    return Counter(results.values())


def main(argv: list[str]) -> None:
    again = "--again" in argv
    packages = [a for a in argv if a != "--again"] or list(PACKAGES)
    unknown = set(packages) - set(PACKAGES)
    if unknown:
        sys.exit(f"unknown package(s) {sorted(unknown)}; choose from {list(PACKAGES)}")
    for package in packages:
        started = time.monotonic()
        counts = run(package, again)
        total, killed = sum(counts.values()), counts.pop("killed", 0)
        rest = "  ".join(f"{status} {n}" for status, n in sorted(counts.items()))
        print(f"{package:10} killed {killed}/{total} ({100 * killed / total:.1f}%)  {rest}  "
              f"in {time.monotonic() - started:.0f} s", flush=True)


if __name__ == "__main__":
    main(sys.argv[1:])
