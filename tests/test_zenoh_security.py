"""The documented secure Zenoh set-up (config/zenoh/), really started: a TLS router with
user/password authentication and access control, the service connected as "service".

Certificates are made in the test with config/zenoh/make-certs.sh (the openssl CLI).
"""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import time
from pathlib import Path

import pytest
import zenoh

from hil_service.listeners.zenoh_shutdown import close_at_exit
from tests.conftest import ROOT, free_tcp_port, free_udp_port
from tests.zenoh_peer import ZenohProbe
from tests.zenoh_router import start_router, stop_router, wait_listening

CONFIGS = ROOT / "config" / "zenoh"

#: Skipped only off CI: .ci/run installs openssl, so there a missing one fails loudly.
pytestmark = pytest.mark.skipif(
    shutil.which("openssl") is None and os.environ.get("CI", "") in ("", "0", "false"),
    reason="needs the openssl CLI (.ci/run installs it)",
)


def _install_configs(directory: Path) -> dict[str, Path]:
    """Certificates and the example configs, with their relative paths made absolute."""
    subprocess.run(["sh", str(CONFIGS / "make-certs.sh"), str(directory / "certs")],
                   check=True, capture_output=True, timeout=60)  # fmt: skip
    shutil.copy(CONFIGS / "credentials.txt", directory / "credentials.txt")
    paths = {}
    for name in ("router", "service", "operator", "observer"):
        text = (CONFIGS / f"{name}.json5").read_text()
        text = text.replace('"certs/', f'"{directory}/certs/')
        text = text.replace('"credentials.txt"', f'"{directory}/credentials.txt"')
        paths[name] = directory / f"{name}.json5"
        paths[name].write_text(text)
    return paths


def _anonymous(endpoint: str, ca: Path, password: str | None = None) -> zenoh.Session:
    config = zenoh.Config()
    config.insert_json5("mode", '"client"')
    config.insert_json5("scouting/multicast/enabled", "false")
    config.insert_json5("connect/endpoints", json.dumps([endpoint]))
    config.insert_json5("connect/timeout_ms", "2000")
    config.insert_json5("transport/link/tls/root_ca_certificate", json.dumps(str(ca)))
    if password is not None:
        config.insert_json5("transport/auth/usrpwd/user", '"operator"')
        config.insert_json5("transport/auth/usrpwd/password", json.dumps(password))
    return close_at_exit(zenoh.open(config))


@pytest.mark.timeout(120)
def test_only_the_authenticated_operator_can_command_the_service(processes, tmp_path):
    configs = _install_configs(tmp_path)
    endpoint = f"tls/127.0.0.1:{free_tcp_port()}"
    udp = free_udp_port()
    router = start_router(endpoint, str(configs["router"]))
    observer = operator = None
    try:
        assert wait_listening(router), "the secured router did not start"
        service = processes.start_service(
            "--mavlink", f"udpin:127.0.0.1:{udp}", "--zenoh-config",
            str(configs["service"]), "--zenoh-connect", endpoint,
            "--log-dir", str(tmp_path / "logs"), "--burn-in", "60",
        )  # fmt: skip
        processes.start(
            "emulate", "--connect", f"udpout:127.0.0.1:{udp}", "--speed", "50",
            "--duration", "100000", "--scenario", "paper", "--seed", "3",
        )  # fmt: skip
        observer = ZenohProbe(endpoint, config_file=str(configs["observer"]))
        assert observer.wait_for(lambda: observer.count("glider/1/umodel/depth") > 80, 30), (
            "an authenticated observer should read the service's publications"
        )

        # Without credentials, or with a wrong password, there is no session at all.
        for password in (None, "guessed"):
            with pytest.raises(zenoh.ZError):
                _anonymous(endpoint, tmp_path / "certs" / "ca.pem", password).close()

        # The observer is authenticated but not allowed to command: the router neither tells
        # it that anyone listens on the command keys nor accepts its puts there.
        observer.put("glider/1/setpoint/depth", {"value": 18.0})
        observer.put("glider/1/control", {"enabled": True})
        time.sleep(2.5)  # a window in which nothing may happen (a negative check)
        health = observer.latest("glider/1/health")
        assert health["control"]["setpoints"]["depth"] is None
        assert health["control"]["enabled"] is False
        assert observer.count("glider/1/command/ballast") == 0

        # The operator is: the same messages make the service command the vehicle.
        operator = ZenohProbe(endpoint, config_file=str(configs["operator"]))
        operator.put("glider/1/setpoint/depth", {"value": 16.0})
        operator.put("glider/1/control", {"enabled": True})
        assert observer.wait_for(lambda: observer.count("glider/1/command/ballast") > 10, 20)
        assert observer.wait_for(
            lambda: observer.latest("glider/1/health")["control"]["setpoints"]["depth"] == 16.0,
            3,
        )
        commands = [c["setpoints"]["depth"] for c in observer.payloads("glider/1/command/ballast")]
        assert set(commands) == {16.0}
        assert service.poll() is None
    finally:
        for probe in (observer, operator):
            if probe is not None:
                probe.close()
        processes.stop_all()
        stop_router(router)
