"""Property-based: random and malformed input to every parser that faces the outside world
(CAN frames and PDO payloads, Zenoh request payloads, model files, CSV recordings). Each must
either work or refuse with its own clear error type; nothing else may escape."""

import json
import math
import tomllib

import can
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from controller.reference import ReferenceError, reference_from_dict
from controller.requests import RequestError, parse_weights
from model.parameters import ModelFileError, default_model_path, load_model
from protocol import cia402, eds_path, telemetry
from protocol import pdo as pdo_layout
from protocol.bus_spec import BusSpecError, parse_bus_spec
from protocol.dictionary import load_dictionary, mappable_object
from recorder.reader import load_recording
from recorder.recording import RecordingError

LIMITS = load_model().limits
DICTIONARY = load_dictionary(eds_path(), 2)
FAST = settings(max_examples=200, deadline=None,
                suppress_health_check=[HealthCheck.function_scoped_fixture])


@FAST
@given(st.binary(max_size=16))
def test_pdo_decoder_takes_any_frame(data):
    for layout in (*pdo_layout.DEFAULT_TPDOS, pdo_layout.RPDO_COMMAND):
        try:
            values = pdo_layout.decode(layout, data)
        except ValueError as exc:
            assert "bytes received" in str(exc)
        else:
            assert pdo_layout.encode(layout, values) == data


@FAST
@given(st.integers(0, 0xFFFF), st.integers(0, 0xFFFF))
def test_cia402_decoding_is_total(statusword, controlword):
    try:
        state = cia402.state_from_statusword(statusword)
    except ValueError:
        return
    command = cia402.command_from_controlword(controlword, 0)
    assert isinstance(cia402.next_state(state, command), cia402.State)


@FAST
@given(st.integers(0, 2**32 - 1))
def test_mapping_entries_are_validated(entry):
    try:
        obj = mappable_object(DICTIONARY, entry)
    except ValueError as exc:
        assert "not mappable" in str(exc)
    else:
        assert obj.mapping_entry == entry


json_values = st.recursive(
    st.none() | st.booleans() | st.floats(allow_nan=True) | st.integers() | st.text(max_size=8),
    lambda children: st.lists(children, max_size=4) | st.dictionaries(st.text(max_size=12),
                                                                      children, max_size=4),
    max_leaves=10)


@FAST
@given(json_values)
def test_reference_requests_are_refused_cleanly(spec):
    try:
        reference = reference_from_dict(spec, LIMITS)
    except ReferenceError:
        return
    low, high = reference.span()
    assert math.isfinite(low) and math.isfinite(high)


@FAST
@given(st.one_of(json_values, st.dictionaries(
    st.sampled_from(["position", "velocity", "current", "torque_barrier", "x"]),
    st.floats(allow_nan=True) | st.integers(-10**9, 10**9), max_size=3)))
def test_weight_requests_are_refused_cleanly(spec):
    try:
        weights = parse_weights(spec)
    except RequestError:
        return
    assert all(0 <= v <= 1e6 for v in weights.values())


@FAST
@given(st.binary(max_size=64))
def test_telemetry_decoding_of_garbage(data):
    from google.protobuf.message import DecodeError

    for name in telemetry.SCHEMAS:
        try:
            telemetry.decode(name, data)
        except DecodeError:
            pass


@FAST
@given(st.text(max_size=40))
def test_bus_specs(spec):
    try:
        kwargs = parse_bus_spec(spec)
    except BusSpecError:
        return
    assert kwargs["interface"] in can.VALID_INTERFACES


BASE = tomllib.loads(default_model_path().read_text())


@settings(max_examples=150, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.sampled_from(sorted(BASE["parameters"])),
       st.one_of(st.floats(allow_nan=True, allow_infinity=False), st.text(max_size=5),
                 st.booleans(), st.integers(-5, 5)),
       st.booleans())
def test_model_files_with_one_bad_value(tmp_path, key, value, drop):
    import tomli_w

    doc = json.loads(json.dumps(BASE))
    if drop:
        del doc["parameters"][key]
    else:
        doc["parameters"][key] = value
    path = tmp_path / "m.toml"
    try:
        path.write_text(tomli_w.dumps(doc))
    except (TypeError, ValueError):
        return  # not representable in TOML at all
    try:
        model = load_model(path)
    except ModelFileError as exc:
        assert str(path) in str(exc) and key in str(exc)
    else:
        assert getattr(model.parameters, key) == value


@settings(max_examples=100, deadline=None,
          suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.text(max_size=300))
def test_csv_reader_takes_any_text(tmp_path, text):
    path = tmp_path / "r.csv"
    path.write_text(text)
    try:
        load_recording(path)
    except RecordingError:
        pass


def test_truncated_and_random_mcap_files_are_refused(tmp_path):
    import random

    rng = random.Random(0)
    for k in range(20):
        path = tmp_path / f"{k}.mcap"
        path.write_bytes(bytes(rng.getrandbits(8) for _ in range(rng.randint(0, 200))))
        with pytest.raises(RecordingError):
            load_recording(path)
