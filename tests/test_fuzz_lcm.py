"""Seeded fuzz of the LCM receive path: mutated encoded messages and mutated signature trailers.

Three layers, each with inputs made from real encoded messages of several types:
- the type registry's decode (``REGISTRY.decode``): only MalformedMessage may come out;
- the bus signature check (``BusAuth.verify``): never raises, and only an intact packet is OK;
- the transport itself over real LCM multicast: packets from a raw LCM publisher (mutated
  payloads signed properly, so they reach decode; signed packets mutated afterwards, so the
  trailer check sees them) handled by ``Transport.handle_once`` in the test thread, so an
  exception escaping the transport's receive path would fail the test; every packet is
  counted as delivered, malformed or rejected, and the callback only ever gets messages of
  the subscribed type.
"""

from __future__ import annotations

import random

from conftest import wait_until
from fuzz_targets import LcmTarget, Mutator, lcm_corpus, run_seeded

from u2sa_hw import lcmtypes as t
from u2sa_hw.bus.auth import OK
from u2sa_hw.messages import REGISTRY, MalformedMessage
from u2sa_hw.bus.transport import Transport


def test_the_registry_decode_raises_only_malformed_message() -> None:
    mutator = Mutator(lcm_corpus(), seed=76, nmea=False)
    decoded = malformed = 0
    for _ in range(150000):
        data = mutator.next()
        try:
            msg, _known = REGISTRY.decode(data, None)
        except MalformedMessage:
            malformed += 1
            continue
        decoded += 1
        assert type(msg).__name__ in REGISTRY.names()
    assert decoded > 1000 and malformed > 1000


def test_the_signature_check_never_raises_and_passes_only_intact_packets(lcm_url: str) -> None:
    tx = Transport(lcm_url, name="fuzz-tx")
    try:
        auth = tx.auth
        assert auth is not None, "the test session signs (conftest sets a bus key)"
        signed = [auth.sign("FUZZ", payload) for payload in lcm_corpus()]
        mutator = Mutator(signed, seed=77)
        verdicts: dict[str, int] = {}
        for _ in range(100000):
            data = mutator.next()
            verdict = auth.verify("FUZZ", data)
            verdicts[verdict] = verdicts.get(verdict, 0) + 1
            if verdict == OK:
                assert any(data == s for s in signed), "a mutated packet passed the signature check"
        assert sum(n for v, n in verdicts.items() if v != OK) > 75000
    finally:
        tx.stop()


def test_the_transport_counts_every_mutated_packet_and_delivers_only_well_typed_ones(lcm_url: str) -> None:
    rx = Transport(lcm_url, name="fuzz-rx")
    signer = Transport(lcm_url, name="fuzz-signer")
    raw = Transport(lcm_url, name="fuzz-raw", security="open")   # publishes the bytes as they are
    got: list[object] = []
    try:
        rx.subscribe("FUZZ_STATE", t.StateInformation, lambda _ch, msg: got.append(msg))
        assert signer.auth is not None
        payloads = lcm_corpus()
        payload_mutator = Mutator(payloads[:1], seed=78)   # StateInformation: the subscribed type
        packet_mutator = Mutator([signer.auth.sign("FUZZ_STATE", p) for p in payloads], seed=79)
        rng = random.Random(80)
        sent = 0
        for batch in range(40):
            for _ in range(50):
                if rng.random() < 0.5:   # a well-signed packet around a mutated message: reaches decode
                    data = signer.auth.sign("FUZZ_STATE", payload_mutator.next())
                else:                    # a signed packet mutated afterwards: the trailer check sees it
                    data = packet_mutator.next()
                raw.publish_bytes("FUZZ_STATE", data)
                sent += 1
            while rx.handle_once(0.05):   # an exception escaping the receive path fails the test here
                pass
        counters = rx.rx["FUZZ_STATE"]

        def all_counted() -> bool:
            rx.handle_once(0.05)
            return counters.messages + counters.malformed + counters.rejected() >= sent
        wait_until(all_counted, timeout=10, message="every packet counted as delivered, malformed or rejected")
        assert counters.messages + counters.malformed + counters.rejected() == sent
        assert counters.malformed > 50 and counters.rejected() > 50 and counters.messages > 50
        assert len(got) == counters.messages
        assert all(isinstance(msg, t.StateInformation) for msg in got)
    finally:
        rx.stop()
        signer.stop()
        raw.stop()


def test_the_bench_target_runs_decode_and_verify_on_mutations(lcm_url: str) -> None:
    """bench/fuzz.py's in-process LCM target: bounded here, long there."""
    target = LcmTarget(lcm_url=lcm_url)
    try:
        assert run_seeded(target, seed=81, count=20000) == 20000 + len(target.corpus)
    finally:
        target.close()
