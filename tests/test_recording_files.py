"""Recording files as users meet them: picked by content, damaged by a flipped bit, cut short,
left by a killed writer, and repaired into files that the standard `mcap` reader opens."""

import ast
import random
import struct
import subprocess
import sys
import time
import tracemalloc
from pathlib import Path

import numpy as np
import pytest
from mcap.reader import make_reader
from mcap.records import Chunk, Message
from mcap.writer import CompressionType, Writer

from protocol import telemetry
from recorder.csv_io import write_csv
from recorder.exciting import ExcitingTrajectory
from recorder.mcap_io import McapRecorder, iter_mcap
from recorder.mcap_records import DataSection, chunk_records
from recorder.reader import load_recording
from recorder.recording import RecordingError
from recorder.repair import repair_recording

CYCLES = 1000  # 1 s at 1 kHz: about ten 16 KiB chunks
METADATA = {"payload_mass": 5.0, "payload_position": "0,0.1", "experiment": "synthetic"}


def synthetic(path: Path, cycles: int = CYCLES, finish: bool = True) -> bytes:
    """A recording as the experiment writes it, without a drive. With finish=False: the bytes
    a SIGKILL at this moment would leave (the file is then discarded unfinished)."""
    writer = McapRecorder(path, METADATA)
    state, command = writer.channel("state", "State"), writer.channel("command", "Command")
    state_class, command_class = (telemetry.message_class("State"),
                                  telemetry.message_class("Command"))
    for k in range(1, cycles + 1):
        t = k * 1e-3
        writer.write(state, state_class(
            t=t, position=-1.2 + 0.8 * np.sin(2 * t), velocity=1.6 * np.cos(2 * t),
            motor_current=-2 + np.sin(t), joint_torque=-9 + np.cos(t), statusword=0x1237,
            drive_state="OPERATION_ENABLED").SerializeToString(), publish_time_ns=k * 10**6)
        writer.write(command, command_class(t=t, current=-2.0).SerializeToString(),
                     publish_time_ns=k * 10**6)
    if finish:
        writer.close()
        return path.read_bytes()
    data = path.read_bytes()
    writer.discard()
    path.write_bytes(data)
    return data


def same(a, b) -> bool:
    return a.metadata == b.metadata and all(
        np.array_equal(getattr(a, name), getattr(b, name))
        for name in ("t", "q", "current", "joint_torque"))


def standard_messages(path: Path) -> list[tuple[str, int, int, bytes]]:
    with open(path, "rb") as fh:
        return [(channel.topic, message.log_time, message.publish_time, message.data)
                for _, channel, message in make_reader(fh).iter_messages(log_time_order=False)]


def chunks(path: Path) -> list[tuple[int, Chunk]]:
    return [(offset, record) for offset, record in DataSection(path).records()
            if isinstance(record, Chunk)]


# --- one reader, picked by content -----------------------------------------------------------

def test_the_reader_modules_do_not_import_each_other():
    folder = Path(__file__).parent.parent / "recorder"

    def imports(module: str) -> set[str]:
        tree = ast.parse((folder / f"{module}.py").read_text())
        return {node.module for node in ast.walk(tree) if isinstance(node, ast.ImportFrom)}

    readers = {"recorder.csv_io", "recorder.mcap_io", "recorder.mcap_records"}
    assert not imports("recording") & (readers | {"recorder.reader"})
    for module in ("csv_io", "mcap_io", "mcap_records"):
        assert "recorder.reader" not in imports(module)
    assert "recorder.mcap_io" not in imports("csv_io")
    assert "recorder.csv_io" not in imports("mcap_io")


def test_the_format_is_picked_by_content_not_by_name(tmp_path):
    mcap = tmp_path / "run.mcap"
    synthetic(mcap)
    renamed = tmp_path / "run.dat"
    renamed.write_bytes(mcap.read_bytes())
    assert same(load_recording(renamed), load_recording(mcap))
    as_csv = tmp_path / "run.txt"
    write_csv(load_recording(mcap), as_csv)
    np.testing.assert_allclose(load_recording(as_csv).q, load_recording(mcap).q, atol=1e-8)
    fake = tmp_path / "fake.mcap"
    fake.write_text(as_csv.read_text())
    with pytest.raises(RecordingError, match="fake.mcap: not an MCAP file"):
        load_recording(fake)


@pytest.mark.parametrize("case,needle", [
    ("directory", "is a directory"),
    ("utf16", "not UTF-8 text"),
    ("binary", "not UTF-8 text"),
])
def test_unreadable_files_are_one_line_naming_the_file(tmp_path, case, needle):
    path = tmp_path / "r.csv"
    if case == "directory":
        path.mkdir()
    elif case == "utf16":
        path.write_text("t,q,current,joint_torque\n0,0,0,0\n", encoding="utf-16")
    else:
        path.write_bytes(bytes(range(256)))
    with pytest.raises(RecordingError) as caught:
        load_recording(path)
    assert str(path) in str(caught.value) and needle in str(caught.value)
    assert "\n" not in str(caught.value)


def test_time_in_milliseconds_is_named(tmp_path):
    path = tmp_path / "ms.csv"
    path.write_text("t,q,current,joint_torque\n" + "".join(
        f"{k},{k * 1e-3},0,0\n" for k in range(1, 100)))
    with pytest.raises(RecordingError, match=r"ms.csv: column t: samples 1 apart; t is in "
                                             r"seconds.*\(time in ms\?\)"):
        load_recording(path)


def test_a_csv_with_a_byte_order_mark_reads(tmp_path):
    path = tmp_path / "excel.csv"
    rows = "".join(f"{k * 1e-3},{k * 1e-3},0,0\n" for k in range(10))
    path.write_text("t,q,current,joint_torque\n" + rows, encoding="utf-8-sig")
    assert len(load_recording(path)) == 10


# --- damage: one line, never a changed value -------------------------------------------------

@pytest.mark.parametrize("finish", [True, False], ids=["complete", "killed"])
def test_two_hundred_bit_flips_read_identically_or_fail_in_one_line(tmp_path, finish):
    data = synthetic(tmp_path / "original.mcap", finish=finish)
    original = load_recording(tmp_path / "original.mcap")
    rng = random.Random(17)
    outcomes = {"identical": 0, "refused": 0}
    chunk_named = 0
    for _ in range(200):
        bit = rng.randrange(len(data) * 8)
        flipped = bytearray(data)
        flipped[bit // 8] ^= 1 << (bit % 8)
        path = tmp_path / "flipped.mcap"
        path.write_bytes(flipped)
        try:
            recording = load_recording(path)
        except RecordingError as exc:  # any other exception type fails the test
            assert "\n" not in str(exc) and str(path) in str(exc)
            outcomes["refused"] += 1
            chunk_named += " chunk " in str(exc)
        else:
            assert same(recording, original), f"byte {bit // 8} bit {bit % 8}: values changed"
            outcomes["identical"] += 1
    assert outcomes["refused"] > 100 and chunk_named > 50, outcomes


def test_a_damaged_chunk_is_named_with_its_offset(tmp_path):
    path = tmp_path / "run.mcap"
    data = bytearray(synthetic(path))
    offset, chunk = chunks(path)[2]
    data[offset + 9 + 40 + len(chunk.data) // 2] ^= 0x10  # in the compressed records
    path.write_bytes(data)
    with pytest.raises(RecordingError, match=rf"run.mcap: chunk 3 at byte {offset}: "):
        load_recording(path)


@pytest.mark.parametrize("compression", [CompressionType.LZ4, CompressionType.NONE])
def test_other_writers_compressions_read_and_their_damage_is_named(tmp_path, compression):
    path = tmp_path / "other.mcap"
    with open(path, "wb") as fh:
        writer = Writer(fh, chunk_size=4096, compression=compression)
        writer.start()
        schema = writer.register_schema(telemetry.schema_name("State"), "protobuf",
                                        telemetry.file_descriptor_set())
        channel = writer.register_channel("state", "protobuf", schema)
        for k in range(1, 501):
            writer.add_message(channel, k, telemetry.message_class("State")(
                t=k * 1e-3, position=k * 1e-4).SerializeToString(), k)
        writer.finish()
    recording = load_recording(path)
    assert len(recording) == 500 and recording.q[-1] == pytest.approx(0.05)
    data = bytearray(path.read_bytes())
    offset, chunk = chunks(path)[1]
    data[offset + 9 + 40 + len(chunk.compression) + len(chunk.data) // 2] ^= 0x04
    path.write_bytes(data)
    with pytest.raises(RecordingError, match=rf"other.mcap: chunk 2 at byte {offset}: "):
        load_recording(path)


def test_huge_length_fields_are_checked_before_anything_is_allocated(tmp_path):
    path = tmp_path / "run.mcap"
    data = synthetic(path)
    offset, chunk = chunks(path)[1]
    body = offset + 9
    fields = {  # where each length sits, by the MCAP spec's layout of a Chunk record
        "record length": offset + 1,
        "uncompressed size": body + 16,
        "compression name length": body + 28,
        "compressed size": body + 32 + len(chunk.compression),
    }
    for name, at in fields.items():
        damaged = bytearray(data)
        damaged[at:at + 8 if name != "compression name length" else at + 4] = (
            struct.pack("<Q", 2**40) if name != "compression name length"
            else struct.pack("<I", 2**31))
        path.write_bytes(damaged)
        tracemalloc.start()
        try:
            with pytest.raises(RecordingError):
                load_recording(path)
            peak = tracemalloc.get_traced_memory()[1]
        finally:
            tracemalloc.stop()
        assert peak < 16 * 2**20, f"{name}: {peak} bytes allocated"


def test_truncated_files_are_refused_naming_the_cut(tmp_path):
    path = tmp_path / "run.mcap"
    data = synthetic(path)
    path.write_bytes(data[:len(data) // 2])
    with pytest.raises(RecordingError, match="truncated MCAP.*recorder repair"):
        load_recording(path)


# --- killed writers and repair ---------------------------------------------------------------

def test_a_killed_writers_file_opens_with_the_standard_reader(tmp_path):
    path = tmp_path / "killed.mcap"
    synthetic(path, finish=False)
    ours = [(m.topic, m.log_time, m.data) for m in iter_mcap(path)]
    assert 0 < len(ours) < 2 * CYCLES  # the open chunk is lost, the flushed ones are there
    with open(path, "rb") as fh:
        assert make_reader(fh).get_summary() is None
    assert [(topic, log_time, data) for topic, log_time, _, data
            in standard_messages(path)] == ours


def test_repair_of_a_killed_file_keeps_every_message_and_adds_the_summary(tmp_path):
    killed, repaired = tmp_path / "killed.mcap", tmp_path / "repaired.mcap"
    synthetic(killed, finish=False)
    report = repair_recording(killed, repaired)
    ours = [(m.topic, m.log_time, m.data) for m in iter_mcap(killed)]
    assert report.messages == len(ours) and not report.dropped_chunks
    assert "killed" in report.ending
    assert [(topic, log_time, data) for topic, log_time, _, data
            in standard_messages(repaired)] == ours
    with open(repaired, "rb") as fh:
        reader = make_reader(fh, validate_crcs=True)
        summary = reader.get_summary()
        assert summary.statistics.message_count == len(ours)
        assert summary.chunk_indexes and {c.topic for c in summary.channels.values()} == {
            "state", "command"}
        assert {m.name: m.metadata for m in reader.iter_metadata()} == {
            "recording": {k: str(v) for k, v in METADATA.items()}}
    assert same(load_recording(repaired), load_recording(killed))


def test_repair_of_a_truncated_file_keeps_every_complete_chunk(tmp_path):
    complete, cut, repaired = (tmp_path / name for name in ("a.mcap", "b.mcap", "c.mcap"))
    data = synthetic(complete)
    located = chunks(complete)
    cut.write_bytes(data[:located[5][0] + 100])  # inside chunk 6
    report = repair_recording(cut, repaired)
    assert report.chunks == 5 and "truncated MCAP" in report.ending
    expected = sum(isinstance(record, Message) for _, chunk in located[:5]
                   for record in chunk_records("", chunk))
    kept = standard_messages(repaired)
    assert len(kept) == expected and kept == standard_messages(complete)[:expected]


def test_repair_drops_a_damaged_chunk_and_names_it(tmp_path):
    path, repaired = tmp_path / "run.mcap", tmp_path / "repaired.mcap"
    data = bytearray(synthetic(path))
    located = chunks(path)
    offset, chunk = located[3]
    data[offset + 9 + 40 + len(chunk.data) // 2] ^= 0x01
    path.write_bytes(data)
    report = repair_recording(path, repaired)
    assert report.chunks == len(located) - 1
    assert len(report.dropped_chunks) == 1 and f"chunk 4 at byte {offset}" in \
        report.dropped_chunks[0]
    assert len(load_recording(repaired)) < CYCLES


def repair_cli(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "commands.recorder", "repair", *args],
                          capture_output=True, text=True, timeout=60)


def test_recorder_repair_command(tmp_path):
    killed, repaired = tmp_path / "killed.mcap", tmp_path / "repaired.mcap"
    synthetic(killed, finish=False)
    proc = repair_cli(str(killed), "-o", str(repaired))
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.count("\n") == 1 and "messages kept" in proc.stdout
    with open(repaired, "rb") as fh:
        assert make_reader(fh).get_summary().statistics.message_count > 0
    csv = tmp_path / "r.csv"
    csv.write_text("t,q,current,joint_torque\n")
    for args, needle in [((str(csv), "-o", str(repaired)), "not an MCAP file"),
                         ((str(killed), "-o", str(killed)), "is the file being repaired"),
                         ((str(killed), "-o", str(tmp_path / "no" / "x.mcap")),
                          "does not exist")]:
        proc = repair_cli(*args)
        lines = proc.stderr.strip().splitlines()
        assert proc.returncode == 2 and len(lines) == 1 and needle in lines[0], proc.stderr


def test_a_recording_that_fails_before_its_first_sample_leaves_no_file(tmp_path):
    output = tmp_path / "run.mcap"
    proc = subprocess.run([sys.executable, "-m", "commands.recorder", "--exciting-trajectory",
                           "--bus", "virtual:nobody-here", "--no-progress", "-o", str(output)],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 1 and "no boot-up message" in proc.stderr
    assert "0 samples" in proc.stdout and "no file written" in proc.stdout
    assert not output.exists()
    proc = subprocess.run([sys.executable, "-m", "commands.recorder", "--exciting-trajectory",
                           "--sim", "-o", str(tmp_path / "missing" / "run.mcap")],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2 and proc.stderr.strip().splitlines() == [
        f"recorder: error: -o {tmp_path / 'missing' / 'run.mcap'}: folder "
        f"{tmp_path / 'missing'} does not exist"]


@pytest.mark.subprocess
def test_a_lockstep_recording_shows_its_true_duration_and_rate(tmp_path):
    """What `mcap info` prints comes from the summary's statistics: a lock-step run (far faster
    than real time) must still span the trajectory's drive time at 1 kHz, dated now."""
    output = tmp_path / "run.mcap"
    started = time.time_ns()
    proc = subprocess.run([sys.executable, "-m", "commands.recorder", "--exciting-trajectory",
                           "--position-low", "-1.5", "--position-high", "-0.9", "--steps", "1",
                           "--velocity-min", "1", "--velocity-max", "1", "--sim", "--lockstep",
                           "--no-progress", "-o", str(output)],
                          capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    with open(output, "rb") as fh:
        reader = make_reader(fh)
        statistics = reader.get_summary().statistics
        channels = reader.get_summary().channels
        messages = [(channels[message.channel_id].topic, message) for _, _, message
                    in reader.iter_messages(log_time_order=False)]
    duration = ExcitingTrajectory(-1.5, -0.9, 1.0, 1.0, 1).duration
    span = (statistics.message_end_time - statistics.message_start_time) / 1e9
    assert abs(span - duration) <= 0.01 * duration, (span, duration)
    state = next(cid for cid, channel in channels.items() if channel.topic.endswith("/state"))
    rate = (statistics.channel_message_counts[state] - 1) / span
    assert abs(rate - 1000) <= 10, rate
    assert abs(statistics.message_start_time - started) < 60e9  # dated now, not 1970
    for topic, message in messages:  # both times: the message's drive time on the run's base
        t = telemetry.decode(telemetry.TOPICS[topic.rsplit("/", 1)[1]], message.data).t
        assert message.publish_time == message.log_time
        assert message.publish_time - statistics.message_start_time == pytest.approx(
            (t - 1e-3) * 1e9, abs=2)


@pytest.mark.parametrize("case,needle", [
    ("binary", "not UTF-8 text"),
    ("directory", "is a directory"),
    ("missing_folder", "does not exist"),
])
def test_recorder_export_refuses_in_one_line(tmp_path, case, needle):
    source, output = tmp_path / "run.mcap", tmp_path / "run.csv"
    synthetic(source, cycles=100)
    if case == "binary":
        source = tmp_path / "blob.bin"
        source.write_bytes(bytes(range(256)) * 4)
    elif case == "directory":
        source = tmp_path
    else:
        output = tmp_path / "missing" / "run.csv"
    proc = subprocess.run([sys.executable, "-m", "commands.recorder", "export", str(source), "-o",
                           str(output)], capture_output=True, text=True, timeout=60)
    lines = proc.stderr.strip().splitlines()
    assert proc.returncode == 2 and len(lines) == 1 and needle in lines[0], proc.stderr
    assert not output.exists()


def test_a_views_bytes_are_recorded_as_its_messages_would_be(tmp_path):
    """The recorder takes a joint's State and Command as the bytes the loop encoded them to
    (`EncodedJointView`, no message built): the file holds what it would hold had it been
    given the messages (same channels, drive-time stamps and bytes), and the part it does not
    record (SolverStats) is left out as a message of its kind would be."""
    from controller import messages
    from controller import workspace as ws
    from model.parameters import load_model

    limits = load_model().limits
    header = [0.0] * ws.HEADER
    header[ws.ITERATIONS], header[ws.PLANNED_CURRENT], header[ws.REFERENCE_POSITION] = 2, 1.5, -1
    written = {}
    for kind in ("messages", "bytes"):
        writer = McapRecorder(tmp_path / f"{kind}.mcap", METADATA)
        record = writer.subscriber(("state", "command", "fault"), telemetry.DEFAULT_PREFIX)
        for k in range(1, 301):
            t = k * 1e-3
            view = messages.joint_view(
                t, [t, -1.2 + np.sin(t), np.cos(t), 1.5, -9 + t, 0x1237],
                "OPERATION_ENABLED", 1.5, [*header[:-1], k], "converged", False, limits, 1e-5)
            if kind == "messages":
                for message in view:
                    record(message)
            else:
                parts = [message.SerializeToString() for message in view]
                ends = tuple(int(end) for end in np.cumsum([len(part) for part in parts]))
                record(messages.EncodedJointView(t, b"".join(parts), ends))
            if k % 100 == 0:
                record(messages.fault(t, "controller", "a fault", "none"))
        writer.close()
        with open(tmp_path / f"{kind}.mcap", "rb") as stream:
            found = [(channel.topic, message.publish_time, message.data) for _, channel, message
                     in make_reader(stream).iter_messages(log_time_order=False)]
        first = found[0][1]
        written[kind] = [(topic, stamp - first, data) for topic, stamp, data in found]
    assert len(written["bytes"]) == 2 * 300 + 3
    assert written["bytes"] == written["messages"]
