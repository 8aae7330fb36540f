"""``pipeline hw``: ping, upload with read-back, emulate."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

from hardware.cli import main
from hardware.led import LedController, LedEmulator, program_crc32

pytestmark = pytest.mark.timeout(30)


def _sequence_file(tmp_path: Path, pattern: list, cycles: int, crc: str | None = None) -> Path:
    path = tmp_path / "sequence.json"
    path.write_text(json.dumps({"pattern": pattern, "cycles": cycles,
                                "program_crc32": crc or program_crc32(pattern, cycles)}))
    return path


def test_ping_and_upload(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    pattern = ["F", 4, 1, "F", 0, 3]
    with LedEmulator(n_bars=5) as emu:
        assert main(["ping", "--port", emu.port, "--count", "2"]) == 0
        assert "5 bars" in capsys.readouterr().out
        path = _sequence_file(tmp_path, pattern, 2)
        assert main(["upload", "--port", emu.port, "--sequence", str(path), "--arm"]) == 0
        out = capsys.readouterr().out
        assert "verified" in out and program_crc32(pattern, 2) in out
        assert emu.firmware.state == "ARMED" and emu.firmware.program.steps == pattern
        assert main(["status", "--port", emu.port]) == 0
        assert json.loads(capsys.readouterr().out)["state"] == "ARMED"


def test_upload_errors_are_one_line_and_an_exit_code(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    with LedEmulator(n_bars=2) as emu:
        path = _sequence_file(tmp_path, ["F", 7], 1)  # bar 7 does not exist on a 2-bar board
        assert main(["upload", "--port", emu.port, "--sequence", str(path)]) == 1
        assert "E06" in capsys.readouterr().err
        stale = _sequence_file(tmp_path, ["F", 1], 1, crc="00000000")
        assert main(["upload", "--port", emu.port, "--sequence", str(stale)]) == 1
        assert "re-run the sequence stage" in capsys.readouterr().err
    assert main(["upload", "--port", "/dev/ttyNO_SUCH", "--sequence", str(tmp_path / "missing.json")]) == 2
    assert main(["ping", "--port", "/dev/ttyNO_SUCH"]) == 1
    assert "cannot open" in capsys.readouterr().err
    assert main(["bogus"]) == 2


def test_emulate_prints_a_port_the_client_can_open() -> None:
    proc = subprocess.Popen([sys.executable, "-c", "import sys; from hardware.cli import main; "
                             "sys.exit(main(['emulate', '--bars', '3', '--seconds', '20']))"],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            cwd=Path(__file__).resolve().parents[3])
    try:
        port = proc.stdout.readline().strip()
        assert port.startswith("/dev/")
        with LedController(port, timeout_s=1.0) as ctl:
            assert ctl.version().bars == 3
    finally:
        proc.terminate()
        proc.wait(timeout=10)
