"""The daemon's typed counters keep the serialised key names status, checkpoints and the
rehearsal report read."""

from dran_edge.daemon.counters import DaemonCounters, IngestCounters


def test_daemon_counters_round_trip_through_the_checkpoint_form():
    c = DaemonCounters()
    c.checkpoints += 2
    c.checkpoint_bytes = 1234
    c.applied["ObservationBatch"] += 3
    c.applied["VioSegment"] += 1
    flat = c.as_dict()
    assert flat["checkpoints"] == 2 and flat["checkpoint_bytes"] == 1234
    assert flat["applied_ObservationBatch"] == 3 and flat["applied_VioSegment"] == 1
    assert flat["recovered_records"] == 0 and flat["send_errors"] == 0
    assert all(isinstance(v, int) for v in flat.values())
    back = DaemonCounters.from_dict(flat)
    assert back == c and back.as_dict() == flat


def test_daemon_counters_read_an_old_checkpoint_with_only_some_keys():
    back = DaemonCounters.from_dict({"messages_sent": 7, "applied_Tick": 2, "not_ours": 1})
    assert back.messages_sent == 7 and back.applied["Tick"] == 2 and back.checkpoints == 0
    assert "not_ours" not in back.as_dict()


def test_ingest_counters_serialise_under_the_status_keys():
    c = IngestCounters()
    c.records += 4
    c.rejected += 1
    assert c.as_dict() == {
        "bytes": 0,
        "records": 4,
        "frames": 0,
        "rejected": 1,
        "clients_accepted": 0,
        "clients_refused": 0,
        "handler_errors": 0,
    }
