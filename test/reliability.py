"""The reliability figures, gathered from the tests that exercise them (``scripts/reliability_figures.sh``).

A test marked ``reliability`` records, through the ``reliability`` fixture, what it did: the bad
inputs it fed a node and how many the node survived (counted, dropped, and the next input
processed), the faults it injected and the places they lost, the drops a node counted. The figures
are therefore exactly what the suite checks; a record of a test that failed is shown as such.
``pytest --reliability-report FILE`` writes them as JSON and prints the tables.
"""

from __future__ import annotations

import json
import os
from collections.abc import Iterator
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import pytest


@dataclass
class Record:
    kind: str  # "bad_inputs" | "fault" | "drops" | "malformed"
    subject: str  # a node's name, or the fault injected
    tried: int = 0  # bad inputs fed / faults injected
    survived: int = 0  # bad inputs the node survived / faults handled: the state reloads whole, or a damaged
    # file is refused with an error and left untouched
    places_lost: int = 0  # faults: places saved before the fault and missing after it
    counts: dict[str, int] = field(default_factory=dict)  # drops: the node's counters; malformed: the verdicts
    kinds: int = 0  # malformed: kinds of malformed message tried
    test: str = ""
    passed: bool = False
    known_defect: bool = False  # its test is a strict xfail: the defect is reported, not yet fixed


class Recorder:
    def __init__(self, test: str, records: list[Record]) -> None:
        self._test = test
        self._records = records

    def bad_inputs(self, node: str, tried: int, survived: int) -> None:
        self._records.append(Record("bad_inputs", node, tried, survived, test=self._test))

    def fault(self, fault: str, injected: int, survived: int, places_lost: int) -> None:
        self._records.append(Record("fault", fault, injected, survived, places_lost, test=self._test))

    def drops(self, node: str, counts: dict[str, int]) -> None:
        self._records.append(Record("drops", node, counts=dict(counts), test=self._test))

    def malformed(self, node: str, verdicts: Any) -> None:
        """A fuzz run's verdicts (test/nodes/topic_probe.Verdicts): messages counted under an expected drop
        name, counted under another, silently accepted, fatal."""
        totals = {name: sum(getattr(verdicts, name).values()) for name in ("counted", "misnamed", "silent", "fatal")}
        self._records.append(Record("malformed", node, tried=sum(totals.values()), survived=totals["counted"],
                                    counts=totals, kinds=len(verdicts.kinds()), test=self._test))


_RECORDS: list[Record] = []


def pytest_addoption(parser: pytest.Parser) -> None:
    parser.addoption("--reliability-report", metavar="FILE", default="",
                     help="write the figures recorded by tests marked 'reliability' to FILE (JSON) and print them")
    parser.addoption("--reliability-markdown", metavar="FILE", default="",
                     help="also write the tables to FILE (markdown, e.g. docs/reliability_figures.md)")


def pytest_configure(config: pytest.Config) -> None:
    config.addinivalue_line("markers", "reliability: records the reliability figures (scripts/reliability_figures.sh)")


@pytest.fixture
def reliability(request: pytest.FixtureRequest) -> Iterator[Recorder]:
    first = len(_RECORDS)
    yield Recorder(request.node.nodeid, _RECORDS)
    report = getattr(request.node, "reliability_call_report", None)
    for record in _RECORDS[first:]:
        record.passed = report is not None and report.passed
        record.known_defect = report is not None and hasattr(report, "wasxfail")


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_makereport(item: pytest.Item, call: pytest.CallInfo[Any]) -> Iterator[None]:
    outcome = yield
    if call.when == "call":
        item.reliability_call_report = outcome.get_result()  # type: ignore[attr-defined]


MALFORMED_HEADER = "Malformed messages through the topics (per node): kinds, messages tried / counted by name / " \
    "counted under another name / silently accepted / fatal  [tests]"


def malformed_rows(records: list[Record]) -> list[tuple[str, int, int, int, int, int, int, str]]:
    rows = []
    for node in sorted({r.subject for r in records if r.kind == "malformed"}):
        mine = [r for r in records if r.kind == "malformed" and r.subject == node]
        failed = sum(not r.passed and not r.known_defect for r in mine)
        known = sum(r.known_defect for r in mine)
        rows.append((node, sum(r.kinds for r in mine), sum(r.tried for r in mine),
                     *(sum(r.counts.get(k, 0) for r in mine) for k in ("counted", "misnamed", "silent", "fatal")),
                     f"{len(mine)} tests{f', {failed} FAILED' if failed else ''}"
                     f"{f', {known} known defect (strict xfail)' if known else ''}"))
    return rows  # type: ignore[return-value]


def tables(records: list[Record]) -> str:
    lines = [MALFORMED_HEADER]
    for node, kinds, tried, counted, misnamed, silent, fatal, tests in malformed_rows(records):
        lines.append(f"  {node:<16} {kinds:>3} kinds  {tried:>4} / {counted:<4} / {misnamed} / {silent} / {fatal}  "
                     f"[{tests}]")
    lines.append("Bad inputs (per node): tried / survived  [tests]")
    for node in sorted({r.subject for r in records if r.kind == "bad_inputs"}):
        mine = [r for r in records if r.kind == "bad_inputs" and r.subject == node]
        failed = sum(not r.passed for r in mine)
        lines.append(f"  {node:<16} {sum(r.tried for r in mine):>4} / {sum(r.survived for r in mine):<4} "
                     f"[{len(mine)} tests{f', {failed} FAILED' if failed else ''}]")
    lines.append("Faults: injected / handled (state whole, or damaged file refused untouched) / places lost  [test]")
    for r in (r for r in records if r.kind == "fault"):
        lines.append(f"  {r.subject:<44} {r.tried:>3} / {r.survived:<3} / {r.places_lost:<3} "
                     f"[{r.test.split('::')[-1]}{'' if r.passed else ', FAILED'}]")
    lines.append("Drops counted (node: counter=value)  [test]")
    for r in (r for r in records if r.kind == "drops"):
        counts = ", ".join(f"{k}={v}" for k, v in sorted(r.counts.items()) if k.startswith(("dropped_", "dds_")))
        lines.append(f"  {r.subject}: {counts or 'none'}  [{r.test.split('::')[-1]}{'' if r.passed else ', FAILED'}]")
    return "\n".join(lines)


def markdown(records: list[Record], command: str) -> str:
    """docs/reliability_figures.md: the malformed-message table, then the other tables as printed, and the command."""
    lines = ["# Reliability figures", "", "Written by `" + command + "` from the tests marked `reliability`: what "
             "each test fed a node, and the node's verdict. Target: no message silently accepted, none fatal.", "",
             "## Malformed messages through the topics", "",
             "Every kind of malformed message a node can get on each topic it subscribes to "
             "(test/nodes/malformed.py), published through ROS to the real node "
             "(test/nodes/test_malformed_inputs.py). A row marked known defect is a strict xfail test: what the "
             "node takes unchecked today, with the drop name it should get.", "",
             "| node | kinds | messages tried | counted by name | counted under another name | silently accepted "
             "| fatal | tests |", "|---|---:|---:|---:|---:|---:|---:|---|"]
    for row in malformed_rows(records):
        lines.append("| " + " | ".join(str(value) for value in row) + " |")
    lines += ["", "## All tables", "", "```", tables(records), "```", ""]
    return "\n".join(lines)


def pytest_terminal_summary(terminalreporter: Any, config: pytest.Config) -> None:
    path = config.getoption("--reliability-report")
    if not path or not _RECORDS:
        return
    Path(path).write_text(json.dumps([asdict(r) for r in _RECORDS], indent=1))
    document = config.getoption("--reliability-markdown")
    if document:
        from aefabmap_ros.io.atomic import atomic_write_text

        atomic_write_text(Path(document), markdown(_RECORDS, os.environ.get("RELIABILITY_COMMAND",
                                                                             "pytest -m reliability")))
    terminalreporter.write_sep("=", "reliability figures")
    terminalreporter.write_line(tables(_RECORDS))
    terminalreporter.write_line(f"(written to {path})")
