#!/usr/bin/env python3
"""Comms benchmark: codec + auth cost against baselines, precision, loopback RADIO/DISH.

    .venv/bin/python tools/bench/bench_comms.py [--quick] [--json] [--auth-only]

``--quick`` (seconds: 50 repetitions, 2 000 poses, 4 loopback rounds at 10 Hz, 0.2 s of
saturation) checks that the script works; its numbers are not the benchmark's.

1. One full round of a robot with 50 separators and 20 objects (SE(3)): encode + sign +
   decode + verify with our codec, side by side with two baselines on the same message in
   the same process: JSON + HMAC-SHA256 and pickle + HMAC-SHA256 (each encode, sign, verify,
   decode). Median over many repetitions; bytes on the wire for each.
1b. Authentication of one robot's round under each key policy (``comms.auth``): fleet HMAC
   against per-robot Ed25519 signatures (``bench_auth``).
2. Codec precision: worst round-trip error of 20 000 random poses within ±100 m.
3. Loopback RADIO→DISH with 6 neighbours at 2 Hz (one centre robot, six neighbours, each its
   own DISH, all in this process; every neighbour answers each round message with a small
   message): per-round round-trip latency (centre encodes+signs and sends → all six decode,
   verify, answer → centre has verified all six answers), delivery, bytes per second; then
   the saturation rate (full rounds back to back). Baseline: the identical exchange (same
   NeighbourLink work) over bare Python UDP sockets in the same run, isolating ZeroMQ's cost.
"""

from __future__ import annotations

import argparse
import hmac
import json
import pickle
import socket
import statistics
import sys
import time

import numpy as np
from dran_edge.comms import codec
from dran_edge.comms.auth import AuthPolicy, Signer, Verifier

from dran_edge import geometry as geo
from dran_edge.messages import NeighbourMessage, ObjectEntry, SeparatorEntry

KEY = bytes(range(32))


def round_message(rng, sender=0, n_sep=50, n_obj=20, round_=1):
    xi = rng.normal(size=(n_sep + n_obj, 6))
    xi[:, :3] *= 30.0
    T = geo.se3_exp(xi)
    stamp = 1_700_000_000_000_000_000 + round_ * 500_000_000
    return NeighbourMessage(
        sender_id=sender,
        round=round_,
        stamp_ns=stamp,
        separators=tuple(
            SeparatorEntry(sender, 1000 + i, stamp - 70_000_000 * i, T[i]) for i in range(n_sep)
        ),
        objects=tuple(ObjectEntry(i, T[n_sep + i], sender, i % 3) for i in range(n_obj)),
    )


def _median_ms(fn, reps):
    fn()
    times = []
    for _ in range(reps):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return 1e3 * statistics.median(times)


def bench_codec(reps):
    rng = np.random.default_rng(0)
    msg = round_message(rng)
    signer = Signer(KEY)
    policy = AuthPolicy(
        fleet_id=1,
        self_id=1,
        fleet_robots=frozenset({0, 1}),
        neighbours=frozenset({0}),
        replay_window=4096,
    )
    state = {"seq": 0}

    def ours():
        verifier = Verifier(KEY, policy)
        grams = codec.encode_datagrams(msg, fleet_id=1, boot_epoch=1, first_sequence=state["seq"])
        state["seq"] += len(grams)
        out = []
        for g in grams:
            got, reason = verifier.check(signer.sign(g.data))
            assert reason is None
            out.append(got)
        return grams

    def as_dict(m):
        return {
            "sender_id": m.sender_id,
            "round": m.round,
            "stamp_ns": m.stamp_ns,
            "separators": [
                [e.owner_robot, e.keyframe_id, e.stamp_ns, e.T_world_body.tolist()]
                for e in m.separators
            ],
            "objects": [
                [e.object_id, e.origin_robot, e.hop_count, e.T_world_object.tolist()]
                for e in m.objects
            ],
        }

    def from_dict(d):
        return NeighbourMessage(
            sender_id=d["sender_id"],
            round=d["round"],
            stamp_ns=d["stamp_ns"],
            separators=tuple(
                SeparatorEntry(o, k, s, np.array(T)) for o, k, s, T in d["separators"]
            ),
            objects=tuple(ObjectEntry(i, np.array(T), o, h) for i, o, h, T in d["objects"]),
        )

    def json_hmac():
        body = json.dumps(as_dict(msg)).encode()
        data = body + hmac.digest(KEY, body, "sha256")
        assert hmac.compare_digest(data[-32:], hmac.digest(KEY, data[:-32], "sha256"))
        from_dict(json.loads(data[:-32]))
        return data

    def pickle_hmac():
        body = pickle.dumps(msg, protocol=pickle.HIGHEST_PROTOCOL)
        data = body + hmac.digest(KEY, body, "sha256")
        assert hmac.compare_digest(data[-32:], hmac.digest(KEY, data[:-32], "sha256"))
        pickle.loads(data[:-32])
        return data

    ours_bytes = sum(len(g.data) for g in ours())
    res = {
        "ours_ms": _median_ms(ours, reps),
        "json_hmac_ms": _median_ms(json_hmac, reps),
        "pickle_hmac_ms": _median_ms(pickle_hmac, reps),
        "ours_bytes": ours_bytes,
        "ours_datagrams": len(ours()),
        "json_bytes": len(json_hmac()),
        "pickle_bytes": len(pickle_hmac()),
        "encode_only_ms": _median_ms(
            lambda: codec.encode_message(msg, fleet_id=1, boot_epoch=1, first_sequence=0), reps
        ),
    }
    res["bytes_by_kind"] = codec.encoded_size(msg).bytes_by_kind
    return res


def bench_auth(reps, degree=3):
    """Authentication cost of one robot's round under each key policy: it signs its round
    message for each of ``degree`` neighbours (one encoding per link, as the delta layout
    sends) and verifies each neighbour's round message. Two rounds: the heavy one above
    (50 separators + 20 objects, 2 datagrams) and a light one (10 + 5, 1 datagram). Only the
    trailer work is timed (encoding and decoding are the codec's, the same for both); median
    over ``reps`` of the wall time and of the process CPU time (robust to other load)."""
    from dran_edge.comms.auth import Ed25519Signer, PairwiseSigner, RobotIdentity, public_key_of
    from dran_edge.comms.pairwise import PairwiseIdentity, PairwiseKeys

    rng = np.random.default_rng(2)
    seeds = {r: bytes([r + 1]) * 32 for r in range(degree + 1)}
    public = {r: (public_key_of(sd),) for r, sd in seeds.items()}
    policy = AuthPolicy(
        fleet_id=1,
        self_id=0,
        fleet_robots=frozenset(seeds),
        neighbours=frozenset(range(1, degree + 1)),
        replay_window=4096,
    )
    out = {"degree": degree}
    for name, (n_sep, n_obj) in (("heavy", (50, 20)), ("light", (10, 5))):
        for pol in ("hmac", "ed25519", "pairwise"):
            signed, pairwise = pol == "ed25519", pol == "pairwise"
            if signed:
                signers = {r: Ed25519Signer(sd) for r, sd in seeds.items()}
                verifier = Verifier(RobotIdentity(seeds[0], public), policy)
            elif pairwise:  # pair keys agreed once at start (not timed: not per round)
                pairs = {
                    r: PairwiseKeys(PairwiseIdentity(sd, public), r, 1) for r, sd in seeds.items()
                }
                signers = {r: PairwiseSigner(k) for r, k in pairs.items()}
                verifier = Verifier(pairs[0], policy)
            else:
                signers = {r: Signer(KEY) for r in seeds}
                verifier = Verifier(KEY, policy)

            def sign(signer, g, to):  # the pairwise policy tags each receiver's copy
                return signer.sign_for(g, to) if pairwise else signer.sign(g)

            own = [
                g.data
                for g in codec.encode_datagrams(
                    round_message(rng, 0, n_sep, n_obj),
                    fleet_id=1,
                    boot_epoch=1,
                    first_sequence=0,
                    signed=signed,
                    pairwise=pairwise,
                )
            ]
            theirs = {
                r: [
                    sign(signers[r], g.data, 0)
                    for g in codec.encode_datagrams(
                        round_message(rng, r, n_sep, n_obj),
                        fleet_id=1,
                        boot_epoch=1,
                        first_sequence=0,
                        signed=signed,
                        pairwise=pairwise,
                    )
                ]
                for r in range(1, degree + 1)
            }

            def one_round(own=own, signer=signers[0], theirs=theirs, verifier=verifier, sign=sign):
                for to in range(1, degree + 1):
                    for g in own:
                        sign(signer, g, to)
                for r, grams in theirs.items():
                    for g in grams:
                        assert verifier._authentic(g, r)

            one_round()
            wall, cpu = [], []
            for _ in range(reps):
                t0, c0 = time.perf_counter(), time.process_time()
                one_round()
                wall.append(time.perf_counter() - t0)
                cpu.append(time.process_time() - c0)
            out[f"{name}_{pol}"] = {
                "datagrams_signed": degree * len(own),
                "datagrams_verified": sum(map(len, theirs.values())),
                "datagram_bytes": [len(g) for g in theirs[1]],
                "wall_ms_median": 1e3 * statistics.median(wall),
                "cpu_ms_median": 1e3 * statistics.median(cpu),
            }
    return out


def bench_precision(n_poses=20_000):
    rng = np.random.default_rng(1)
    T = geo.se3_from_rt(
        geo.so3_exp(rng.normal(size=(n_poses, 3)) * 2.0), rng.uniform(-100, 100, size=(n_poses, 3))
    )
    msg = NeighbourMessage(
        sender_id=0,
        round=0,
        stamp_ns=0,
        objects=tuple(ObjectEntry(i, T[i], 0) for i in range(len(T))),
    )
    grams = codec.encode_message(
        msg, fleet_id=1, boot_epoch=0, first_sequence=0, max_datagram_bytes=codec.HARD_CAP_BYTES
    )
    out = np.stack([e.T_world_object for g in grams for e in codec.decode_datagram(g).objects])
    pos = np.abs(out[:, :3, 3] - T[:, :3, 3]).max()
    rot = np.linalg.norm(
        geo.so3_log(np.swapaxes(out[:, :3, :3], -1, -2) @ T[:, :3, :3]), axis=-1
    ).max()
    return {
        "poses": len(T),
        "max_position_error_m": float(pos),
        "max_rotation_error_rad": float(rot),
    }


def _free_ports(n):
    socks = [socket.socket(socket.AF_INET, socket.SOCK_DGRAM) for _ in range(n)]
    for s in socks:
        s.bind(("127.0.0.1", 0))
    ports = [s.getsockname()[1] for s in socks]
    for s in socks:
        s.close()
    return ports


class PlainUdpTransport:
    """Baseline only: the Transport interface over a bare non-blocking UDP socket."""

    def __init__(self, port, neighbours):
        from dran_edge.comms.counters import CommCounters

        self.counters = CommCounters()
        self.sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.sock.bind(("127.0.0.1", port))
        self.sock.setblocking(False)
        self.neighbours = {j: ("127.0.0.1", p) for j, p in neighbours.items()}

    def send(self, to, data):
        self.sock.sendto(data, self.neighbours[to])
        self.counters.sent(to, len(data))
        return True

    def receive(self, max_datagrams=None):
        out = []
        while True:
            try:
                out.append((None, self.sock.recv(65536)))
            except BlockingIOError:
                return out

    def close(self):
        self.sock.close()


def bench_radio(rounds, rate_hz, saturate_s, plain_udp=False):
    from dran_edge.comms.link import NeighbourLink
    from dran_edge.comms.radio import RadioParams, RadioTransport

    n_nb = 6
    ids = list(range(n_nb + 1))
    ports = dict(zip(ids, _free_ports(len(ids))))
    ep = {i: f"udp://127.0.0.1:{ports[i]}" for i in ids}
    neigh = {0: {j: ep[j] for j in ids[1:]}, **{j: {0: ep[0]} for j in ids[1:]}}
    if plain_udp:
        transports = {i: PlainUdpTransport(ports[i], {j: ports[j] for j in neigh[i]}) for i in ids}
    else:
        transports = {
            i: RadioTransport(
                RadioParams(
                    group="dran.bench", bind=ep[i], neighbours=neigh[i], max_datagram_bytes=1200
                )
            )
            for i in ids
        }
    links = {
        i: NeighbourLink(
            transports[i],
            key=KEY,
            boot_epoch=1,
            policy=AuthPolicy(
                fleet_id=1, self_id=i, fleet_robots=frozenset(ids), neighbours=frozenset(neigh[i])
            ),
        )
        for i in ids
    }
    time.sleep(0.3)
    rng = np.random.default_rng(2)

    def one_round(k):
        msg = round_message(rng, sender=0, round_=k)
        t0 = time.perf_counter()
        links[0].send_message(msg, ids[1:])
        answered: set = set()
        per_nb_msgs = {j: 0 for j in ids[1:]}
        deadline = t0 + 1.0
        while len(answered) < n_nb and time.perf_counter() < deadline:
            for j in ids[1:]:
                for m in links[j].poll():
                    per_nb_msgs[j] += 1
                    if per_nb_msgs[j] == 2:  # the round spans two datagrams
                        reply = NeighbourMessage(
                            sender_id=j,
                            round=k,
                            stamp_ns=m.stamp_ns,
                            objects=(ObjectEntry(j, np.eye(4), j),),
                        )
                        links[j].send_message(reply, [0])
            for m in links[0].poll():
                answered.add(m.sender_id)
        return time.perf_counter() - t0, len(answered)

    rtts, delivered = [], 0
    period = 1.0 / rate_hz
    next_t = time.perf_counter()
    t_start = time.perf_counter()
    for k in range(rounds):
        next_t += period
        rtt, got = one_round(k)
        if got == n_nb:
            rtts.append(rtt)
        delivered += got
        time.sleep(max(next_t - time.perf_counter(), 0.0))
    elapsed = time.perf_counter() - t_start
    sent_bytes = links[0].counters.totals()["bytes_sent"]
    res = {
        "rounds": rounds,
        "rate_hz": rate_hz,
        "neighbours": n_nb,
        "answers_received": delivered,
        "answers_expected": rounds * n_nb,
        "rtt_ms_median": 1e3 * statistics.median(rtts),
        "rtt_ms_p95": 1e3 * float(np.percentile(rtts, 95)),
        "centre_bytes_per_s": sent_bytes / elapsed,
        "centre_datagrams_sent": links[0].counters.totals()["datagrams_sent"],
        "rejected_total": sum(links[i].counters.totals()["datagrams_rejected"] for i in ids),
    }
    # Saturation: full rounds back to back.
    n, t_end = 0, time.perf_counter() + saturate_s
    lost = 0
    while time.perf_counter() < t_end:
        _, got = one_round(rounds + n)
        lost += n_nb - got
        n += 1
    res["saturation_rounds_per_s"] = n / saturate_s
    res["saturation_answers_lost"] = lost
    for t in transports.values():
        t.close()
    return res


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument(
        "--quick",
        action="store_true",
        help="seconds: few repetitions and rounds (checks the script, not speed)",
    )
    ap.add_argument("--json", action="store_true", help="print one JSON object")
    ap.add_argument(
        "--auth-only",
        action="store_true",
        help="only the authentication cost per round (section 1b)",
    )
    a = ap.parse_args(argv)
    if a.auth_only:
        res = bench_auth(100 if a.quick else 500)
        print(json.dumps(res, indent=2))
        return 0
    reps, poses, rounds, rate_hz, saturate_s = (
        (50, 2_000, 4, 10.0, 0.2) if a.quick else (2000, 20_000, 40, 2.0, 2.0)
    )
    res = {
        "codec": bench_codec(reps),
        "auth": bench_auth(20 if a.quick else 500),
        "precision": bench_precision(poses),
    }
    try:
        res["radio"] = bench_radio(rounds, rate_hz, saturate_s)
        res["udp_baseline"] = bench_radio(rounds, rate_hz, saturate_s, plain_udp=True)
    except Exception as exc:  # noqa: BLE001 - a bench reports what it could not run
        res["radio_error"] = f"{type(exc).__name__}: {exc}"
    if a.json:
        print(json.dumps(res, indent=2))
        return 0
    c = res["codec"]
    print("== full round, 50 separators + 20 objects (SE(3)), encode+sign+decode+verify")
    print(
        f"  ours          {c['ours_ms']:.3f} ms  {c['ours_bytes']:6d} B in {c['ours_datagrams']} datagrams"
    )
    print(
        f"  json+hmac     {c['json_hmac_ms']:.3f} ms  {c['json_bytes']:6d} B   "
        f"(ours: {c['json_hmac_ms'] / c['ours_ms']:.1f}x faster, {c['json_bytes'] / c['ours_bytes']:.1f}x smaller)"
    )
    print(
        f"  pickle+hmac   {c['pickle_hmac_ms']:.3f} ms  {c['pickle_bytes']:6d} B   "
        f"(ours: {c['pickle_hmac_ms'] / c['ours_ms']:.2f}x the time, {c['pickle_bytes'] / c['ours_bytes']:.1f}x smaller)"
    )
    print(f"  encode only   {c['encode_only_ms']:.3f} ms; bytes by kind {c['bytes_by_kind']}")
    au = res["auth"]
    print(
        f"== authentication of one round: sign own round message for {au['degree']} "
        f"neighbours + verify {au['degree']} neighbours' (trailer work only, median)"
    )
    for name in ("heavy", "light"):
        h, e, pw = au[f"{name}_hmac"], au[f"{name}_ed25519"], au[f"{name}_pairwise"]
        print(
            f"  {name:5s} ({e['datagrams_signed']} signed + {e['datagrams_verified']} verified, "
            f"datagrams {e['datagram_bytes']} B signed / {h['datagram_bytes']} B hmac): "
            f"ed25519 {e['wall_ms_median']:.3f} ms wall, {e['cpu_ms_median']:.3f} ms CPU; "
            f"pairwise {pw['wall_ms_median']:.3f} ms wall, {pw['cpu_ms_median']:.3f} ms CPU; "
            f"hmac {h['wall_ms_median']:.3f} ms wall, {h['cpu_ms_median']:.3f} ms CPU "
            f"(ed25519 {e['cpu_ms_median'] / max(h['cpu_ms_median'], 1e-9):.0f}x, pairwise "
            f"{pw['cpu_ms_median'] / max(h['cpu_ms_median'], 1e-9):.1f}x the fleet HMAC)"
        )
    p = res["precision"]
    print(
        f"== precision over {p['poses']} poses within ±100 m: position {p['max_position_error_m']:.2e} m, "
        f"rotation {p['max_rotation_error_rad']:.2e} rad"
    )
    if "radio" in res:
        r, u = res["radio"], res["udp_baseline"]
        print(
            f"== loopback RADIO->DISH, {r['neighbours']} neighbours at {r['rate_hz']:g} Hz, {r['rounds']} rounds"
        )
        print(
            f"  round trip (send round to 6, all 6 answers verified): median {r['rtt_ms_median']:.2f} ms, "
            f"p95 {r['rtt_ms_p95']:.2f} ms"
        )
        print(
            f"  baseline, same link work over plain Python UDP sockets: median "
            f"{u['rtt_ms_median']:.2f} ms, p95 {u['rtt_ms_p95']:.2f} ms "
            f"(RADIO/DISH {r['rtt_ms_median'] / u['rtt_ms_median']:.2f}x); saturation "
            f"{u['saturation_rounds_per_s']:.0f} rounds/s"
        )
        print(
            f"  answers {r['answers_received']}/{r['answers_expected']}, centre sends "
            f"{r['centre_bytes_per_s'] / 1e3:.1f} kB/s, rejected {r['rejected_total']}"
        )
        print(
            f"  saturation: {r['saturation_rounds_per_s']:.0f} full rounds/s "
            f"({r['saturation_rounds_per_s'] / 2.0:.0f}x the 2 Hz a robot needs), answers lost "
            f"{r['saturation_answers_lost']}"
        )
    else:
        print("== loopback RADIO->DISH not run: " + res["radio_error"])
    return 0


if __name__ == "__main__":
    sys.exit(main())
