"""deploy/'s TLS router works as written: mutual TLS with certificates made by
deploy/make-certs.sh, and access control by certificate common name.

On loopback: the router runs deploy/zenoh-router-tls.json5 (certificate paths pointed at the
test's own, made by the script), a real ``swanky-relay --config relay.yaml`` (whose
``zenoh.config`` is deploy/zenoh-relay-tls.json5) replays a bag, clients open sessions through
the commands' own flags (``--zenoh-config deploy/zenoh-host-tls.json5``, ``--cfg`` for another
certificate) as ``swanky-host`` does, and ``swanky-host --list`` runs with that file. The listed
host gets every byte; a client without a certificate, with one from another CA, or with one the
access list does not name, gets none and reaches nobody. ``swanky-host --workers 2`` through the
same router converts each of two robots in its own worker.
"""

from __future__ import annotations

import socket
import ssl
import subprocess
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import pytest
import zenoh
from zenoh import ext

from robot_relay.errors import ConfigError
from robot_relay.wire import Catalog, catalog_key, data_key, data_selector
from tests.integration.procs import command, free_port, open_loopback, running
from tests.integration.robot_bags import STORE, Entry, Lines, string, write_bag
from tests.reliability import Record
from tests.rrd import entity_rows

pytestmark = pytest.mark.integration

DEPLOY = Path(__file__).resolve().parents[2] / "deploy"
CERTS_IN_DEPLOY = "/etc/swanky/certs"
ROBOT = "tb3"
CHATTER = 20
HOST, INTRUDER, RELAY = "host-lab-pc", "host-intruder", "relay-tb3"
URDF = '<robot name="secure"><link name="base_link"/></robot>'
# How long a sample that should not arrive is given to arrive anyway, after one that should
# have (sent later on the same route) did: on loopback it takes milliseconds.
GRACE_S = 1.0


def chatter_payloads() -> list[bytes]:
    return [bytes(STORE.serialize_cdr(string(f"hello {i}"), "std_msgs/msg/String"))
            for i in range(CHATTER)]


def forged(writer: str) -> bytes:
    return bytes(STORE.serialize_cdr(string(f"forged by {writer}"), "std_msgs/msg/String"))


def make_certs(directory: Path, *names: str) -> str:
    out = subprocess.run(["sh", str(DEPLOY / "make-certs.sh"), "-d", str(directory), *names],
                         check=True, capture_output=True, text=True, timeout=60)
    return out.stdout


@dataclass
class Lab:
    """The router's endpoint, the certificates and the deploy/ configs pointed at them."""

    directory: Path
    certs: Path
    endpoint: str = ""
    router: zenoh.Session | None = None

    def config(self, name: str) -> Path:
        """deploy/``name`` with the certificate paths of this lab, in the lab's directory."""
        path = self.directory / name
        path.write_text((DEPLOY / name).read_text().replace(CERTS_IN_DEPLOY, str(self.certs)))
        return path

    def client(self, cert: str | None, certs: Path | None = None) -> zenoh.Session:
        """A session as ``swanky-host --zenoh-config zenoh-host-tls.json5 -e ENDPOINT`` opens
        it, presenting ``cert`` (a make-certs.sh name) or no certificate at all."""
        folder = certs or self.certs
        if cert is None:
            chosen = ["--cfg", "transport/link/tls/enable_mtls:false",
                      "--cfg", "transport/link/tls/connect_certificate:null",
                      "--cfg", "transport/link/tls/connect_private_key:null"]
        else:
            chosen = ["--cfg", f'transport/link/tls/connect_certificate:"{folder / cert}.pem"',
                      "--cfg", f'transport/link/tls/connect_private_key:"{folder / cert}.key"']
        return open_loopback("--zenoh-config", str(self.config("zenoh-host-tls.json5")),
                             "-e", self.endpoint, *chosen)


@pytest.fixture(scope="module")
def lab(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Lab]:
    directory = tmp_path_factory.mktemp("security")
    lab = Lab(directory, directory / "certs")
    make_certs(lab.certs, RELAY, HOST, INTRUDER)
    # Another lab's CA, signing a certificate with the same name as ours.
    make_certs(directory / "rogue", RELAY)
    config = zenoh.Config.from_file(str(lab.config("zenoh-router-tls.json5")))
    port = free_port()
    config.insert_json5("listen/endpoints", f'["tls/127.0.0.1:{port}"]')
    lab.router = zenoh.open(config)
    # The name clients check against the router's certificate (make-certs.sh's default).
    lab.endpoint = f"tls/localhost:{port}"
    yield lab
    lab.router.close()


@dataclass
class Received:
    """Samples a subscriber got, by key; thread-safe, waitable."""

    samples: list[tuple[str, bytes]] = field(default_factory=list)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def __call__(self, sample: zenoh.Sample) -> None:
        with self.lock:
            self.samples.append((str(sample.key_expr), sample.payload.to_bytes()))

    def on(self, key: str) -> list[bytes]:
        with self.lock:
            return [payload for k, payload in self.samples if k == key]

    def wait_for(self, condition: Callable[[], bool], what: str, timeout: float = 60) -> None:
        deadline = time.monotonic() + timeout
        while not condition():
            assert time.monotonic() < deadline, f"{what} within {timeout} s; got {self.samples}"
            time.sleep(0.05)


def replies(session: zenoh.Session, key: str) -> list[bytes]:
    return [r.ok.payload.to_bytes() for r in session.get(key, timeout=3.0) if r.ok is not None]


def test_make_certs_makes_a_ca_a_router_and_client_certificates(lab: Lab) -> None:
    def field_of(cert: Path, *option: str) -> str:
        out = subprocess.run(["openssl", "x509", "-in", str(cert), "-noout", *option],
                             check=True, capture_output=True, text=True, timeout=30)
        return out.stdout.strip()

    names = ("router", RELAY, HOST, INTRUDER)
    verify = subprocess.run(
        ["openssl", "verify", "-CAfile", str(lab.certs / "ca.pem"),
         *(str(lab.certs / f"{n}.pem") for n in names)],
        check=False, capture_output=True, text=True, timeout=30)
    assert verify.stdout.splitlines() == [f"{lab.certs / n}.pem: OK" for n in names]
    assert field_of(lab.certs / f"{RELAY}.pem", "-subject") == f"subject=CN = {RELAY}"
    assert field_of(lab.certs / "router.pem", "-subject") == "subject=CN = localhost"
    alt = field_of(lab.certs / "router.pem", "-ext", "subjectAltName").splitlines()
    assert alt[1].strip() == "DNS:localhost, IP Address:127.0.0.1"
    assert "TLS Web Client Authentication" in field_of(lab.certs / f"{RELAY}.pem", "-ext",
                                                       "extendedKeyUsage")
    # The rogue lab's certificate has our relay's name but not our CA's signature.
    rogue = subprocess.run(["openssl", "verify", "-CAfile", str(lab.certs / "ca.pem"),
                            str(lab.directory / "rogue" / f"{RELAY}.pem")],
                           check=False, capture_output=True, text=True, timeout=30)
    assert rogue.returncode != 0
    # Private keys are readable by their owner only; running again keeps the CA.
    for name in ("ca", *names):
        assert (lab.certs / f"{name}.key").stat().st_mode & 0o777 == 0o600
    ca = (lab.certs / "ca.pem").read_bytes()
    again = make_certs(lab.directory / "certs-again", "relay-x")
    assert "new CA" in again
    assert "new CA" not in make_certs(lab.directory / "certs-again", "relay-y")
    assert (lab.certs / "ca.pem").read_bytes() == ca


def test_listed_host_gets_the_relay_data_and_no_one_else_reads_or_writes(
    lab: Lab, tmp_path: Path, reliability: Record
) -> None:
    payloads = chatter_payloads()
    bag = write_bag(tmp_path / "bag", [
        Entry("/robot_description", "std_msgs/msg/String", 0, string(URDF), 1),
        *(Entry("/chatter", "std_msgs/msg/String", 10_000_000 * (i + 1), string(f"hello {i}"))
          for i in range(CHATTER)),
    ])
    relay_yaml = tmp_path / "relay.yaml"
    relay_config = lab.config("zenoh-relay-tls.json5")
    relay_yaml.write_text(f"robot: {ROBOT}\nzenoh:\n  config: {relay_config}\n"
                          f"  connect: [{lab.endpoint}]\n")
    chatter_key = data_key(ROBOT, "/chatter")

    # Certified but not listed, and a relay's certificate reading like a host: both subscribe
    # first. (A relay's certificate may publish under swanky/**: that is what relays do.)
    intruder, other_relay = lab.client(INTRUDER), lab.client(RELAY)
    host, other_host = lab.client(HOST), lab.client(HOST)
    sessions = [intruder, other_relay, host, other_host]
    try:
        intruder_got, relay_cert_got, host_got = Received(), Received(), Received()
        intruder.declare_subscriber("swanky/**", intruder_got)
        other_relay.declare_subscriber("swanky/**", relay_cert_got)
        with running(command("robot_relay.cli", "--config", str(relay_yaml), "--bag", str(bag),
                             "--wait-for-host", "60", "--hold", "inf")) as relay:
            lines = Lines(relay)
            host.declare_subscriber(data_selector(ROBOT), host_got)
            host_got.wait_for(lambda: len(host_got.on(chatter_key)) == CHATTER,
                              f"{CHATTER} /chatter samples at the host")
            lines.wait_for(f"replay finished, {CHATTER + 1} messages sent", timeout=30)
            (catalog_bytes,) = replies(host, catalog_key(ROBOT))
            catalog = Catalog.from_json(catalog_bytes, catalog_key(ROBOT))
            # A host that starts after the replay gets the latched model from the relay's cache
            # (zenoh-ext's @adv keys pass the access list too).
            late_got = Received()
            late = ext.declare_advanced_subscriber(
                other_host, data_selector(ROBOT), late_got,
                history=ext.HistoryConfig(detect_late_publishers=True))
            description_key = data_key(ROBOT, "/robot_description")
            late_got.wait_for(lambda: bool(late_got.on(description_key)), "the latched model")

            # The host command itself, through the same configuration file.
            listing = subprocess.run(
                command("host_bridge.cli", "--zenoh-config", str(lab.config("zenoh-host-tls.json5")),
                        "-e", lab.endpoint, "--list", "--duration", "2"),
                check=False, capture_output=True, text=True, timeout=60)
            # Writes by clients that may not publish; the catalog replies that follow travel the
            # same route, and GRACE_S more is given.
            for session, name in ((intruder, INTRUDER), (other_host, HOST)):
                for _ in range(CHATTER):
                    session.put(chatter_key, forged(name))
            intruder_catalog = replies(intruder, catalog_key(ROBOT))
            relay_cert_catalog = replies(other_relay, catalog_key(ROBOT))
            assert len(replies(host, catalog_key(ROBOT))) == 1
            time.sleep(GRACE_S)
            late.undeclare()
            assert "Traceback" not in lines.text
    finally:
        for session in sessions:
            session.close()

    assert host_got.on(chatter_key) == payloads  # every byte, in order, nothing forged
    assert late_got.on(description_key) == [
        bytes(STORE.serialize_cdr(string(URDF), "std_msgs/msg/String"))]
    assert sorted(t.topic for t in catalog.topics) == ["/chatter", "/robot_description"]
    assert listing.returncode == 0, listing.stderr
    assert [line.split()[:4] for line in listing.stdout.splitlines()[1:]] == [
        [ROBOT, "/chatter", "std_msgs/msg/String", "reliable"],
        [ROBOT, "/robot_description", "std_msgs/msg/String", "reliable,"],  # ", latched"
    ], listing.stdout
    # Its own puts, which its session delivers to its own subscriber without the router.
    assert intruder_got.samples == [(chatter_key, forged(INTRUDER))] * CHATTER
    assert relay_cert_got.samples == []
    assert (intruder_catalog, relay_cert_catalog) == ([], [])
    reliability(
        "Security", "a listed host (certificate CN host-lab-pc) reads a relay over mutual TLS",
        tried=f"1 replay of {CHATTER} messages + 1 latched, a catalog query, a late host",
        survived=f"{CHATTER}/{CHATTER} payloads byte-exact and in order, the catalog, the "
        "latched model to the late host (once)", lost="0")
    reliability(
        "Security", "a certified client the access list does not name (CN host-intruder)",
        tried=f"subscribe swanky/**, query the catalog, {CHATTER} forged puts",
        survived=f"it received 0 of the relay's {CHATTER + 1} samples and 0 catalog replies; "
        f"the host received 0 of its {CHATTER} puts", lost="0")
    reliability(
        "Security", "a relay's certificate used to read, a listed host's to write",
        tried=f"relay cert: subscribe swanky/** + catalog query; host cert: {CHATTER} puts "
        "on the relay's key", survived=f"the relay cert received 0 samples, 0 replies; the "
        f"other host received 0 of the {CHATTER} puts", lost="0")


def test_clients_without_a_valid_certificate_get_zero_bytes(lab: Lab, reliability: Record) -> None:
    # No certificate at all; our relay's name signed by another CA.
    for cert, certs in ((None, None), (RELAY, lab.directory / "rogue")):
        with pytest.raises(ConfigError, match="cannot open a zenoh session"):
            lab.client(cert, certs=certs).close()
    # Plain TCP to the TLS port: no Zenoh session either.
    with pytest.raises(ConfigError, match="cannot open a zenoh session"):
        open_loopback("-m", "client", "-e", lab.endpoint.replace("tls/", "tcp/")).close()

    # Below Zenoh: a TLS client that trusts our CA but has no certificate reads nothing at all
    # (TLS 1.3: the server's refusal arrives as the first record).
    context = ssl.create_default_context(cafile=str(lab.certs / "ca.pem"))
    port = int(lab.endpoint.rsplit(":", 1)[1])
    read = b""
    with socket.create_connection(("127.0.0.1", port), timeout=10) as raw, \
            context.wrap_socket(raw, server_hostname="localhost") as tls:
        tls.sendall(b"\x00" * 64)
        with pytest.raises(ssl.SSLError, match="CERTIFICATE_REQUIRED"):
            read += tls.recv(4096)
    assert read == b""

    # The router still serves the clients it should.
    relay, host = lab.client(RELAY), lab.client(HOST)
    try:
        got = Received()
        host.declare_subscriber(data_selector(ROBOT), got)
        key = data_key(ROBOT, "/after")
        got.wait_for(lambda: (relay.put(key, b"still here"), bool(got.on(key)))[1],
                     "a sample through the router after the refusals")
    finally:
        relay.close()
        host.close()
    reliability(
        "Security", "clients without a valid certificate connect to the TLS router",
        tried="4: a Zenoh client without certificate, one with our relay's name signed by "
        "another CA, plain TCP, a raw TLS socket without certificate",
        survived="all 4 refused at the handshake (the raw socket: alert certificate_required); "
        "the router then served a listed host", lost="0 bytes reached them; they published 0")


def test_workers_behind_the_tls_router_convert_every_robot_once(lab: Lab, tmp_path: Path) -> None:
    """``swanky-host --workers 2`` through the lab's TLS router: its main process is the
    router's client with the host's certificate, and its workers, reaching the robots only
    through that process, each convert their own robot (tb3 and tb4 fall in different shards)."""
    robots = (ROBOT, "tb4")
    relays = []
    for robot in robots:
        bag = write_bag(tmp_path / f"bag-{robot}", [
            Entry("/chatter", "std_msgs/msg/String", 10_000_000 * (i + 1), string(f"{robot} {i}"))
            for i in range(CHATTER)])
        relay_yaml = tmp_path / f"relay-{robot}.yaml"
        relay_yaml.write_text(f"robot: {robot}\nzenoh:\n  config: {lab.config('zenoh-relay-tls.json5')}\n"
                              f"  connect: [{lab.endpoint}]\n")
        relays.append(command("robot_relay.cli", "--config", str(relay_yaml), "--bag", str(bag),
                              "--wait-for-host", "60", "--hold", "inf"))
    saved = tmp_path / "fleet.rrd"
    host_command = command(
        "host_bridge.cli", "--zenoh-config", str(lab.config("zenoh-host-tls.json5")),
        "-e", lab.endpoint, "--no-rmw-zenoh", "--workers", "2", "--save", str(saved),
        "--duration", "20")
    with running(host_command) as host, running(relays[0]) as first, running(relays[1]) as second:
        for relay in (first, second):
            Lines(relay).wait_for(f"replay finished, {CHATTER} messages sent", timeout=60)
        out, _ = host.communicate(timeout=90)
    assert host.returncode == 0, out
    texts: dict[tuple[str, str], list[str]] = {}
    for worker in ("worker0", "worker1"):
        for entity, rows in entity_rows(tmp_path / f"fleet-{worker}.rrd").items():
            if entity.endswith("/chatter"):
                texts[worker, entity] = [text for row in rows for text in row["TextLog:text"]]
    assert texts == {
        ("worker1", f"/{ROBOT}/chatter"): [f"{ROBOT} {i}" for i in range(CHATTER)],
        ("worker0", "/tb4/chatter"): [f"tb4 {i}" for i in range(CHATTER)],
    }
