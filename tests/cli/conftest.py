"""Prints the bad-input matrix (tests/cli/test_bad_inputs.py) by category at the end of the session."""


def pytest_terminal_summary(terminalreporter) -> None:
    from tests.cli.test_bad_inputs import MATRIX

    if not MATRIX:
        return
    terminalreporter.section("bad-input matrix (issue 18)")
    total = passed = 0
    for category in sorted(MATRIX):
        cases = MATRIX[category]
        ok = sum(cases.values())
        total, passed = total + len(cases), passed + ok
        terminalreporter.write_line(f"{category:<28} {ok:4d} / {len(cases):<4d} one-line named errors, exit 2")
        for name, good in cases.items():
            if not good:
                terminalreporter.write_line(f"    FAILED: {name}")
    terminalreporter.write_line(f"{'total':<28} {passed:4d} / {total:<4d} ({100 * passed / total:.1f} %)")
