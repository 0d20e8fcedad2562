"""Mutual TLS between the sites (link.zenoh.tls): a third process without a certificate of
the sites' CA, publishing on the keys the HSI listens to, changes nothing at the HSI: it never
connects, so nothing of it arrives (and the same intruder without TLS is seen and rejected)."""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest

from tests.conftest import CONFIGS
from tests.test_zenoh_sites import free_port

pytest.importorskip("zenoh")
if shutil.which("openssl") is None:
    pytest.skip("openssl is not installed", allow_module_level=True)

PAPER = CONFIGS / "paper_experiment.yaml"


def openssl(*args: str, cwd: Path) -> None:
    subprocess.run(["openssl", *args], cwd=cwd, check=True, capture_output=True, timeout=60)


def make_pki(d: Path) -> None:
    """A CA, a certificate for each site signed by it (subjectAltName localhost, as the
    endpoints name the host), and a self-signed one for the intruder."""
    openssl("req", "-x509", "-newkey", "rsa:2048", "-nodes", "-keyout", "ca.key", "-out",
            "ca.pem", "-days", "2", "-subj", "/CN=teleop-rt test CA", cwd=d)  # fmt: skip
    (d / "san.ext").write_text("subjectAltName=DNS:localhost\n")
    for name in ("hsi", "to"):
        openssl("req", "-newkey", "rsa:2048", "-nodes", "-keyout", f"{name}.key", "-out",
                f"{name}.csr", "-subj", f"/CN={name}", cwd=d)  # fmt: skip
        openssl("x509", "-req", "-in", f"{name}.csr", "-CA", "ca.pem", "-CAkey", "ca.key",
                "-CAcreateserial", "-out", f"{name}.pem", "-days", "2", "-extfile", "san.ext",
                cwd=d)  # fmt: skip
    openssl("req", "-x509", "-newkey", "rsa:2048", "-nodes", "-keyout", "rogue.key", "-out",
            "rogue.pem", "-days", "2", "-subj", "/CN=localhost", "-addext",
            "subjectAltName=DNS:localhost", cwd=d)  # fmt: skip


INTRUDER = textwrap.dedent(
    """
    import sys, time
    sys.path.insert(0, {root!r})
    from teleop_rt.com.zenoh_transport import zenoh_config
    import zenoh
    tls = {tls!r}
    c = zenoh_config([], [{endpoint!r}], tls)
    s = zenoh.open(c)
    pub = s.declare_publisher({key!r})
    end = time.monotonic() + {seconds}
    while time.monotonic() < end:
        pub.put(bytes(128))  # what a stranger would send: never a valid packet of ours
        time.sleep(0.002)
    s.close()
    """
)


def run_pair(tmp: Path, port: int, scheme: str, tls_args: list[str], intruder_tls) -> dict:
    endpoint = f"{scheme}/localhost:{port}"
    args = ["--set", f"link.zenoh.hsi.listen=[{endpoint}]",
            "--set", f"link.zenoh.to.connect=[{endpoint}]", *tls_args]  # fmt: skip
    intruder = tmp / f"intruder-{scheme}.py"
    intruder.write_text(INTRUDER.format(root=str(Path(__file__).resolve().parents[1]),
                                        tls=intruder_tls, endpoint=endpoint, seconds=25,
                                        key="teleop_rt/paper_experiment/to/waves"))  # fmt: skip
    cmd = [sys.executable, "-m", "teleop_rt", "run", str(PAPER), "--link", "zenoh", "--realtime",
           "--duration", "4", "--json", "--set", "channel.delay_ms=20", *args]  # fmt: skip
    rogue = subprocess.Popen([sys.executable, str(intruder)], stdout=subprocess.DEVNULL,
                             stderr=subprocess.PIPE, text=True)  # fmt: skip
    try:
        out = subprocess.run(cmd, capture_output=True, text=True, timeout=240, cwd=tmp)
    finally:
        rogue.kill()
        rogue.communicate()
    assert out.returncode == 0, out.stderr[-3000:]
    return json.loads(out.stdout)


def test_a_peer_without_the_sites_certificate_never_reaches_the_hsi(tmp_path: Path) -> None:
    make_pki(tmp_path)
    tls = [
        f"--set=link.zenoh.tls={{root_ca: {tmp_path}/ca.pem, "
        f"hsi: {{certificate: {tmp_path}/hsi.pem, private_key: {tmp_path}/hsi.key}}, "
        f"to: {{certificate: {tmp_path}/to.pem, private_key: {tmp_path}/to.key}}}}"
    ]
    rogue_tls = {"root_ca": str(tmp_path / "rogue.pem"), "certificate": str(tmp_path / "rogue.pem"),
                 "private_key": str(tmp_path / "rogue.key")}  # fmt: skip
    guarded = run_pair(tmp_path, free_port(), "tls", tls, rogue_tls)
    hsi = guarded["sites"]["hsi"]["link"]["from_peer"]
    assert guarded["pair"]["ticks"] == 4000
    assert hsi["received"] > 0.95 * 4000 and hsi["rejected"] == 0, hsi  # the TO's only
    # the same intruder on a plain UDP link gets through to the HSI: its packets are rejected
    # there (not ours), so the check above can tell
    open_link = run_pair(tmp_path, free_port(), "udp", [], None)
    seen = open_link["sites"]["hsi"]["link"]["from_peer"]
    assert seen["rejected"] > 100, seen
