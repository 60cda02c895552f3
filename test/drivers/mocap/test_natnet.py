"""NatNet codec: hand-built packets, round trips per stream version, robustness, UDP loopback."""
import socket
import struct
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings, strategies as st

from soft_arm_drivers.mocap.natnet import (ITEM_LIMITS, AnalogData, ConnectRequest, FrameFilter, FrameOfData,
                                           LabeledMarker, MarkerSet, MessageId, NatNetParseError, RigidBody,
                                           ServerInfo, Skeleton, Version, build_connect_request,
                                           build_frame_of_data, build_packet, build_request,
                                           build_server_info, parse_connect_request, parse_frame_of_data,
                                           parse_packet, parse_server_info)
from soft_arm_drivers.mocap.natnet_scan import scan_frame_of_data

VERSIONS = [Version(3, 1), Version(4, 0), Version(4, 1)]
ALL_SUPPORTED = [Version(3, 0), *VERSIONS]


def packet(message_id, payload):
    return struct.pack("<HH", message_id, len(payload)) + payload


def hand_built_frame(version):
    """Frame 42: one rigid body, one occluded labelled marker, written field by field."""
    sized = version >= (4, 1)

    def section(count, body=b""):
        return struct.pack("<i", count) + (struct.pack("<i", len(body)) if sized else b"") + body

    rigid_body = struct.pack("<i3f4ffh", 7, 0.5, -1.0, 2.0, 0.0, 0.0, 0.0, 1.0, 0.25, 0x01)
    marker = struct.pack("<i3ffhf", 7 << 16 | 3, 1.0, 2.0, 3.0, 0.015625, 0x01, 0.5)
    payload = b"".join([
        struct.pack("<i", 42),                                  # frame number
        section(0),                                             # marker sets
        section(0),                                             # legacy unlabelled markers
        section(1, rigid_body),                                 # rigid bodies
        section(0),                                             # skeletons
        struct.pack("<ii", 0, 0) if sized else b"",             # assets (4.1)
        section(1, marker),                                     # labelled markers
        section(0),                                             # force plates
        section(0),                                             # devices
        struct.pack("<IId", 0x01020304, 5, 12.5),               # timecode, subframe, timestamp
        struct.pack("<QQQ", 10_000, 10_100, 10_200),            # mid-exposure, received, transmit
        struct.pack("<II", 1_700_000_000, 99) if sized else b"",  # precision timestamp (4.1)
        struct.pack("<h", 0x02),                                # params: models changed
        struct.pack("<i", 0),                                   # end-of-data tag
    ])
    return packet(7, payload)


EXPECTED_HAND_BUILT = FrameOfData(
    frame_number=42,
    rigid_bodies=(RigidBody(7, (0.5, -1.0, 2.0), (0.0, 0.0, 0.0, 1.0), 0.25, 0x01),),
    labeled_markers=(LabeledMarker(7 << 16 | 3, (1.0, 2.0, 3.0), 0.015625, 0x01, 0.5),),
    timecode=0x01020304, timecode_subframe=5, timestamp=12.5, camera_mid_exposure=10_000,
    camera_data_received=10_100, transmit_timestamp=10_200, params=0x02)


def expected_for(version):
    if version >= (4, 1):
        return replace(EXPECTED_HAND_BUILT, precision_timestamp_secs=1_700_000_000,
                       precision_timestamp_frac_secs=99)
    return EXPECTED_HAND_BUILT


# --- hand-built bytes ----------------------------------------------------------------------------

@pytest.mark.parametrize("version", ALL_SUPPORTED, ids=str)
def test_parse_hand_built_frame(version):
    frame = parse_frame_of_data(hand_built_frame(version), version)
    assert frame == expected_for(version)
    body, = frame.rigid_bodies
    assert body.tracking_valid
    marker, = frame.labeled_markers
    assert marker.occluded and (marker.model_id, marker.marker_id) == (7, 3)
    assert frame.tracked_models_changed and not frame.is_recording


@pytest.mark.parametrize("version", ALL_SUPPORTED, ids=str)
def test_builder_reproduces_hand_built_bytes(version):
    assert build_frame_of_data(version, expected_for(version)) == hand_built_frame(version)


def test_v41_asset_data_set_is_skipped_by_its_size():
    data = hand_built_frame(Version(4, 1))
    empty_assets = struct.pack("<ii", 0, 0)
    opaque_assets = struct.pack("<ii", 1, 20) + bytes(range(20))
    payload = data[4:].replace(empty_assets + struct.pack("<ii", 1, 26), opaque_assets
                               + struct.pack("<ii", 1, 26))
    assert len(payload) == len(data) - 4 + 20
    assert parse_frame_of_data(packet(7, payload), Version(4, 1)) == expected_for(Version(4, 1))


def test_end_of_data_tag_is_optional():
    data = hand_built_frame(Version(3, 1))
    assert parse_frame_of_data(packet(7, data[4:-4]), Version(3, 1)) == EXPECTED_HAND_BUILT


def test_server_info_hand_built():
    payload = (b"Motive".ljust(256, b"\0") + bytes([3, 1, 0, 0]) + bytes([4, 1, 0, 0])
               + struct.pack("<QH?4B", 10_000_000, 1511, True, 233, 252, 0, 1))
    info = parse_server_info(packet(1, payload))
    assert info == ServerInfo("Motive", Version(3, 1), Version(4, 1), clock_frequency=10_000_000,
                              data_port=1511, multicast=True, multicast_group="233.252.0.1")
    assert build_server_info(info) == packet(1, payload)


def test_connect_request_layout():
    data = build_connect_request("soft_arm", bitstream_version=(4, 1))
    message_id, size = struct.unpack_from("<HH", data)
    payload = data[4:]
    assert (message_id, size, len(payload)) == (0, 273, 273)  # sSender + sConnectionOptions + 4
    assert payload[:256] == b"soft_arm".ljust(256, b"\0")
    assert payload[256:264] == bytes(8)
    assert payload[264:269] == bytes([0, 4, 1, 0, 0])
    assert parse_connect_request(data) == ConnectRequest("soft_arm", Version(4, 1), False)


def test_parse_connect_request_of_other_clients():
    # The SDK's Python client: "Ping", options at byte 264, 270 bytes plus a trailing NUL.
    sdk_python = bytearray(270)
    sdk_python[:4] = b"Ping"
    sdk_python[265:269] = bytes([4, 1, 0, 0])
    assert parse_connect_request(packet(0, bytes(sdk_python) + b"\0")) == ConnectRequest(
        "Ping", Version(4, 1, 0, 0), False)
    assert parse_connect_request(packet(0, b"")) == ConnectRequest("")
    assert parse_connect_request(packet(0, b"Ping\0")) == ConnectRequest("Ping")
    assert parse_connect_request(packet(0, b"client".ljust(264, b"\0"))) == ConnectRequest("client")
    assert parse_connect_request(build_connect_request(subscribed_data_only=True)) == ConnectRequest(
        "soft_arm", None, True)


def test_build_request_and_packet():
    assert build_request("Bitstream,4.1") == struct.pack("<HH", 2, 14) + b"Bitstream,4.1\0"
    assert build_packet(MessageId.NAT_KEEPALIVE) == bytes([10, 0, 0, 0])
    # The SDK's Python client sends keep-alives declaring 0 bytes followed by a NUL: ignored.
    assert parse_packet(bytes([10, 0, 0, 0, 0])) == (MessageId.NAT_KEEPALIVE, b"")


# --- round trips ---------------------------------------------------------------------------------

f32 = st.floats(width=32, allow_nan=False)
i32 = st.integers(-(2 ** 31), 2 ** 31 - 1)
u16 = st.integers(0, 0xFFFF)
u32 = st.integers(0, 2 ** 32 - 1)
u64 = st.integers(0, 2 ** 64 - 1)
vec3 = st.tuples(f32, f32, f32)
rigid_bodies = st.builds(RigidBody, i32, vec3, st.tuples(f32, f32, f32, f32), f32, u16)
labeled_markers = st.builds(LabeledMarker, i32, vec3, f32, u16, f32)
analogs = st.builds(AnalogData, i32, st.lists(st.lists(f32, max_size=3).map(tuple), max_size=3)
                    .map(tuple))
names = st.text(st.characters(blacklist_characters="\0", codec="utf-8"), max_size=8)


@st.composite
def frames(draw, version, size=4):
    def some(elements):
        return tuple(draw(st.lists(elements, max_size=size)))

    precision = (draw(u32), draw(u32)) if version >= (4, 1) else (0, 0)
    return FrameOfData(
        frame_number=draw(i32),
        rigid_bodies=some(rigid_bodies),
        labeled_markers=some(labeled_markers),
        marker_sets=some(st.builds(MarkerSet, names, st.lists(vec3, max_size=size).map(tuple))),
        unlabeled_markers=some(vec3),
        skeletons=some(st.builds(Skeleton, i32, st.lists(rigid_bodies, max_size=2).map(tuple))),
        force_plates=some(analogs),
        devices=some(analogs),
        timecode=draw(u32), timecode_subframe=draw(u32),
        timestamp=draw(st.floats(allow_nan=False)), camera_mid_exposure=draw(u64),
        camera_data_received=draw(u64), transmit_timestamp=draw(u64),
        precision_timestamp_secs=precision[0], precision_timestamp_frac_secs=precision[1],
        params=draw(u16))


@pytest.mark.parametrize("version", VERSIONS, ids=str)
def test_round_trip_rigid_bodies_and_markers(version):
    frame = FrameOfData(
        frame_number=1234,
        rigid_bodies=(RigidBody(1, (0.1, 0.2, 0.3), (0.0, 0.0, 0.70710677, 0.70710677), 1e-4, 1),
                      RigidBody(2, (-1.5, 0.0, 2.25), (0.0, 0.0, 0.0, 1.0), 0.0, 0)),
        labeled_markers=(LabeledMarker(1 << 16 | 1, (0.5, 0.5, 0.5), 0.014, 0x04, 2e-4),
                         LabeledMarker(1 << 16 | 2, (0.0, 0.0, 0.0), 0.014, 0x01, 0.0)),
        timestamp=3.25, camera_mid_exposure=2 ** 40 + 7, camera_data_received=2 ** 40 + 9,
        transmit_timestamp=2 ** 40 + 11)
    parsed = parse_frame_of_data(build_frame_of_data(version, frame), version)
    assert parsed.frame_number == 1234 and parsed.timestamp == 3.25
    assert parsed.camera_mid_exposure == 2 ** 40 + 7
    assert [b.tracking_valid for b in parsed.rigid_bodies] == [True, False]
    assert [m.occluded for m in parsed.labeled_markers] == [False, True]
    for got, sent in zip(parsed.rigid_bodies, frame.rigid_bodies):
        assert got.position == pytest.approx(sent.position, rel=1e-7)
        assert got.orientation == pytest.approx(sent.orientation, rel=1e-7)
    assert parsed.labeled_markers[0].position == (0.5, 0.5, 0.5)


@pytest.mark.parametrize("version", VERSIONS, ids=str)
@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.data())
def test_round_trip_property(version, data):
    frame = data.draw(frames(version))
    assert parse_frame_of_data(build_frame_of_data(version, frame), version) == frame


@settings(max_examples=60, deadline=None)
@given(st.text(st.characters(blacklist_characters="\0", codec="utf-8"), max_size=40).filter(
    lambda s: len(s.encode()) < 256), st.tuples(*[st.integers(0, 255)] * 4), st.integers(3, 255),
    st.integers(0, 2 ** 64 - 1), st.integers(0, 0xFFFF), st.booleans(), st.ip_addresses(v=4))
def test_server_info_round_trip(name, app_version, major, frequency, port, multicast, group):
    info = ServerInfo(name, Version(*app_version), Version(major, 1), frequency, port, multicast,
                      str(group))
    assert parse_server_info(build_server_info(info)) == info


def test_legacy_server_info_has_no_connection_fields():
    info = ServerInfo("Motive", Version(1, 10), Version(2, 10))
    data = build_server_info(info)
    assert len(data) == 4 + 264
    assert parse_server_info(data) == info


# --- robustness ----------------------------------------------------------------------------------

def _parses_or_raises(data, version):
    try:
        assert isinstance(parse_frame_of_data(data, version), FrameOfData)
    except NatNetParseError:
        pass


@pytest.mark.parametrize("version", VERSIONS, ids=str)
@settings(max_examples=150, deadline=None)
@given(noise=st.binary(max_size=300))
def test_random_bytes_never_escape(version, noise):
    _parses_or_raises(noise, version)
    _parses_or_raises(packet(7, noise), version)


RICH_FRAME = FrameOfData(
    frame_number=9, marker_sets=(MarkerSet("arm", ((0.0, 1.0, 2.0), (3.0, 4.0, 5.0))), MarkerSet("")),
    unlabeled_markers=((1.0, 1.0, 1.0),),
    rigid_bodies=(RigidBody(1, (1.0, 2.0, 3.0), (0.0, 0.0, 0.0, 1.0)), RigidBody(2, (0, 0, 0), (1, 0, 0, 0))),
    skeletons=(Skeleton(4, (RigidBody(5, (1.0, 0.0, 0.0), (0.0, 1.0, 0.0, 0.0)),)), Skeleton(6)),
    labeled_markers=(LabeledMarker(65537, (0.5, 0.5, 0.5), 0.01, 0x06, 0.001),),
    force_plates=(AnalogData(1, ((1.0, 2.0), (), (3.0,))),), devices=(AnalogData(2, ((0.5,),)),),
    timestamp=1.0, camera_mid_exposure=1, camera_data_received=2, transmit_timestamp=3, params=1)


@st.composite
def mutated(draw, version):
    """A valid frame, then truncated, overwritten or extended; header fixed up or left stale."""
    base = draw(st.sampled_from([hand_built_frame(version), build_frame_of_data(version, RICH_FRAME)]))
    payload = bytearray(base[4:])
    for _ in range(draw(st.integers(1, 4))):
        operation = draw(st.sampled_from(["truncate", "overwrite", "insert", "int32"]))
        at = draw(st.integers(0, len(payload)))
        if operation == "truncate":
            del payload[at:]
        elif operation == "overwrite" and at < len(payload):
            payload[at] = draw(st.integers(0, 255))
        elif operation == "insert":
            payload[at:at] = draw(st.binary(min_size=1, max_size=8))
        elif operation == "int32":  # absurd or negative counts and sizes
            value = draw(st.sampled_from([-1, -(2 ** 31), 2 ** 31 - 1, 2 ** 20, 65535]))
            payload[at:at + 4] = struct.pack("<i", value)
    data = packet(7, bytes(payload[:0xFFFF]))
    if draw(st.booleans()):
        data = data[:2] + struct.pack("<H", draw(st.integers(0, 0xFFFF))) + data[4:]
    return data


@settings(max_examples=300, deadline=None)
@given(data=st.data())
def test_mutated_frames_parse_or_raise_parse_error(data):
    version = data.draw(st.sampled_from(VERSIONS))
    _parses_or_raises(data.draw(mutated(version)), version)


@pytest.mark.parametrize("version", ALL_SUPPORTED, ids=str)
def test_every_truncation_of_a_valid_frame_is_rejected(version):
    data = hand_built_frame(version)
    for end in range(len(data) - 4):  # dropping only the end-of-data tag is still valid
        with pytest.raises(NatNetParseError):
            parse_frame_of_data(packet(7, data[4:end]), version)
        with pytest.raises(NatNetParseError):
            parse_frame_of_data(data[:end], version)


@settings(max_examples=150, deadline=None)
@given(st.binary(max_size=300))
def test_handshake_parsers_never_escape(noise):
    for parse, message_id in ((parse_server_info, 1), (parse_connect_request, 0)):
        for data in (noise, packet(message_id, noise)):
            try:
                parse(data)
            except NatNetParseError:
                pass


@pytest.mark.parametrize("count_offset", [4, 8, 12])
def test_absurd_counts_are_rejected_without_allocating(count_offset):
    # Offsets of the marker set, legacy marker and rigid body counts in a 3.1 frame.
    payload = bytearray(hand_built_frame(Version(3, 1))[4:])
    payload[count_offset:count_offset + 4] = struct.pack("<i", 2 ** 31 - 1)
    with pytest.raises(NatNetParseError, match="implausible"):
        parse_frame_of_data(packet(7, bytes(payload)), Version(3, 1))


def test_negative_count_is_rejected():
    payload = bytearray(hand_built_frame(Version(4, 0))[4:])
    payload[12:16] = struct.pack("<i", -1)  # rigid body count
    with pytest.raises(NatNetParseError, match="implausible rigid body count -1"):
        parse_frame_of_data(packet(7, bytes(payload)), Version(4, 0))


def test_v41_size_mismatch_is_rejected():
    payload = bytearray(hand_built_frame(Version(4, 1))[4:])
    rigid_body_size_at = 4 + 8 + 8 + 4  # frame number, two empty sets, rigid body count
    assert struct.unpack_from("<i", payload, rigid_body_size_at) == (38,)
    for size, match in ((36, "implausible rigid body count 1 with 36 bytes"),
                        (40, "byte size says 40 but its 1 items take 38")):
        payload[rigid_body_size_at:rigid_body_size_at + 4] = struct.pack("<i", size)
        with pytest.raises(NatNetParseError, match=match):
            parse_frame_of_data(packet(7, bytes(payload)), Version(4, 1))


def test_trailing_garbage_is_rejected():
    data = hand_built_frame(Version(3, 1))
    with pytest.raises(NatNetParseError, match="unexpected bytes"):
        parse_frame_of_data(packet(7, data[4:] + b"\0"), Version(3, 1))


def test_version_mismatch_is_detected():
    # A 4.1 frame read as 4.0 (the mocap_optitrack failure mode) must not parse silently.
    with pytest.raises(NatNetParseError):
        parse_frame_of_data(hand_built_frame(Version(4, 1)), Version(4, 0))


@pytest.mark.parametrize("data, match", [
    (b"", "shorter than the 4-byte header"),
    (b"\x07\x00\x10", "shorter than the 4-byte header"),
    (struct.pack("<HH", 42, 0), "unknown NatNet message id 42"),
    (struct.pack("<HH", 7, 100) + bytes(10), "declares 100 payload bytes"),
    (packet(5, bytes(8)), "expected NAT_FRAMEOFDATA"),
])
def test_bad_packets_are_rejected(data, match):
    with pytest.raises(NatNetParseError, match=match):
        parse_frame_of_data(data, Version(4, 1))


@pytest.mark.parametrize("version", [(2, 9), (4, 2), (5, 0), Version(3, 2)])
def test_unsupported_versions(version):
    with pytest.raises(NatNetParseError, match="unsupported NatNet stream version"):
        parse_frame_of_data(hand_built_frame(Version(4, 1)), version)
    with pytest.raises(ValueError, match="unsupported NatNet stream version"):
        build_frame_of_data(version, FrameOfData(1))


@pytest.mark.parametrize("payload, match", [
    (bytes(263), "264 or 279 bytes"),
    (bytes(280), "264 or 279 bytes"),
    (bytes(260) + bytes([4, 1, 0, 0]), "lacks the connection fields"),
])
def test_bad_server_info_is_rejected(payload, match):
    with pytest.raises(NatNetParseError, match=match):
        parse_server_info(packet(1, payload))
    with pytest.raises(NatNetParseError, match="expected NAT_SERVERINFO"):
        parse_server_info(build_connect_request())


@pytest.mark.parametrize("frame, match", [
    (FrameOfData(2 ** 31), "does not fit"),
    (FrameOfData(1, rigid_bodies=(RigidBody(1, (0, 0, 0), (0, 0, 0, 1), 0.0, 0x10000),)),
     "does not fit"),
    (FrameOfData(1, marker_sets=(MarkerSet("a\0b"),)), "NUL"),
    (FrameOfData(1, precision_timestamp_secs=5), "no precision timestamp"),
    (FrameOfData(1, unlabeled_markers=((0.0, 0.0, 0.0),) * 6000), "exceeds 65535"),
])
def test_builder_rejects_unrepresentable_frames(frame, match):
    with pytest.raises(ValueError, match=match):
        build_frame_of_data(Version(3, 1), frame)


@pytest.mark.parametrize("info, match", [
    (ServerInfo("x" * 256, Version(1, 0), Version(4, 1), 1, 1, True, "1.2.3.4"), "at most 255"),
    (ServerInfo("Motive", Version(1, 0), Version(4, 1)), "needs clock_frequency"),
    (ServerInfo("Motive", Version(1, 0), Version(2, 9), clock_frequency=1), "no connection fields"),
    (ServerInfo("Motive", Version(1, 0), Version(4, 1), 1, 70000, True, "1.2.3.4"), "wire format"),
    (ServerInfo("Motive", Version(1, 0), Version(4, 1), 1, 1, True, "1.2.3"), "wire format"),
    (ServerInfo("Motive", Version(256, 0), Version(4, 1), 1, 1, True, "1.2.3.4"), "app_version"),
])
def test_server_info_builder_validates(info, match):
    with pytest.raises(ValueError, match=match):
        build_server_info(info)


# --- frame filter --------------------------------------------------------------------------------

def test_filter_counts_duplicates_and_out_of_order_frames():
    frame_filter = FrameFilter()
    accepted = [n for n in [10, 11, 11, 13, 12, 14, 14, 9, 15] if frame_filter.accept(n)]
    assert accepted == [10, 11, 13, 14, 15]
    assert (frame_filter.accepted, frame_filter.duplicates, frame_filter.out_of_order,
            frame_filter.restarts) == (5, 2, 2, 0)
    assert frame_filter.newest == 15


def test_filter_accepts_a_stream_restart():
    frame_filter = FrameFilter(restart_gap=100)
    assert [frame_filter.accept(n) for n in [5000, 4950, 3, 4, 4]] == [True, False, True, True, False]
    assert (frame_filter.restarts, frame_filter.out_of_order, frame_filter.duplicates) == (1, 1, 1)
    frame_filter.reset()
    assert frame_filter.newest is None and frame_filter.accepted == 0
    assert frame_filter.accept(1)


def test_filter_takes_a_take_looped_within_the_gap_as_a_restart_and_late_datagrams_as_late():
    """A recorded take of 500 frames loops (Motive's playback): the stream counts up from its start
    again, well within the gap; its third frame on is accepted as a restart. Late datagrams, alone
    or two in a row, are refused; so are a row that does not count up by one, one datagram
    overtaken by three (they are close behind the newest), and late frames that would count up only
    across a frame accepted between them."""
    frame_filter = FrameFilter()
    take = list(range(1, 501))
    accepted = [n for n in take + take[:10] if frame_filter.accept(n)]
    assert accepted == take + take[2:10]
    assert (frame_filter.restarts, frame_filter.out_of_order, frame_filter.newest) == (1, 2, 10)
    late = FrameFilter()
    accepted = [n for n in [100, 101, 99, 102, 98, 99, 103, 90, 92, 94, 104] if late.accept(n)]
    assert accepted == [100, 101, 102, 103, 104]
    assert (late.restarts, late.out_of_order) == (0, 6)
    for frames, accepted in (([100, 104, 101, 102, 103, 105], [100, 104, 105]),
                             ([100, 101, 102, 80, 103, 81, 82, 104], [100, 101, 102, 103, 104])):
        late = FrameFilter()
        assert [n for n in frames if late.accept(n)] == accepted and late.restarts == 0


def test_filter_rejects_bad_gap():
    with pytest.raises(ValueError, match="restart_gap"):
        FrameFilter(restart_gap=0)
    with pytest.raises(ValueError, match="restart_run"):
        FrameFilter(restart_run=1)
    with pytest.raises(ValueError, match="reorder_window"):
        FrameFilter(restart_gap=10, reorder_window=10)


# --- UDP loopback --------------------------------------------------------------------------------

def test_handshake_and_frame_over_udp_loopback():
    """Connect, server info and one 4.1 frame over real unicast UDP sockets on 127.0.0.1."""
    frame = FrameOfData(
        frame_number=77, rigid_bodies=(RigidBody(3, (0.25, 0.5, 0.75), (0.0, 0.0, 0.0, 1.0)),),
        labeled_markers=(LabeledMarker(3 << 16 | 1, (0.25, 0.5, 1.0), 0.015625),), timestamp=0.5,
        camera_mid_exposure=123_456_789, precision_timestamp_secs=1, precision_timestamp_frac_secs=2)
    with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as server, \
            socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as client:
        for sock in (server, client):
            sock.bind(("127.0.0.1", 0))
            sock.settimeout(2.0)
        client.sendto(build_connect_request(bitstream_version=(4, 1)), server.getsockname())
        request, client_address = server.recvfrom(65535)
        requested = parse_connect_request(request).bitstream_version
        server.sendto(build_server_info(ServerInfo(
            "Emulator", Version(1, 0), requested, clock_frequency=10_000_000,
            data_port=server.getsockname()[1], multicast=False, multicast_group="0.0.0.0")),
            client_address)
        version = parse_server_info(client.recv(65535)).natnet_version
        server.sendto(build_frame_of_data(version, frame), client_address)
        received = client.recv(65535)
    assert version == Version(4, 1)
    assert parse_frame_of_data(received, version) == frame


# --- the bridge's compiled scan agrees with the parser --------------------------------------------

def _agree(data, version):
    """parse_frame_of_data and scan_frame_of_data refuse the same datagrams and read the same
    rigid bodies, labelled markers and time stamps from the others."""
    try:
        parsed = parse_frame_of_data(data, version)
    except NatNetParseError:
        with pytest.raises(NatNetParseError):
            scan_frame_of_data(data, version)
        return
    scan = scan_frame_of_data(data, version)
    assert scan.frame_number == parsed.frame_number
    assert (scan.camera_mid_exposure, scan.camera_data_received, scan.transmit_timestamp) == (
        parsed.camera_mid_exposure, parsed.camera_data_received, parsed.transmit_timestamp)
    assert scan.timestamp == parsed.timestamp or (scan.timestamp != scan.timestamp)        # NaN
    assert [int(i) for i in scan.rigid_bodies["id"]] == [b.id for b in parsed.rigid_bodies]
    assert [int(p) for p in scan.rigid_bodies["params"]] == [b.params for b in parsed.rigid_bodies]
    np.testing.assert_array_equal(scan.rigid_bodies["position"].reshape(-1, 3),
                                  np.array([b.position for b in parsed.rigid_bodies]).reshape(-1, 3))
    assert [int(i) for i in scan.labeled_markers["id"]] == [m.id for m in parsed.labeled_markers]
    assert [int(p) for p in scan.labeled_markers["params"]] == [m.params for m in parsed.labeled_markers]


@pytest.mark.parametrize("version", VERSIONS, ids=str)
@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(data=st.data())
def test_the_scan_reads_what_the_parser_reads(version, data):
    _agree(build_frame_of_data(version, data.draw(frames(version))), version)


@settings(max_examples=500, deadline=None)
@given(data=st.data())
def test_the_scan_refuses_what_the_parser_refuses(data):
    version = data.draw(st.sampled_from(VERSIONS))
    _agree(data.draw(mutated(version)), version)
    _agree(packet(7, data.draw(st.binary(max_size=120))), version)


@pytest.mark.parametrize("version", ALL_SUPPORTED, ids=str)
def test_every_truncation_is_refused_by_the_scan_too(version):
    data = hand_built_frame(version)
    for end in range(len(data) - 4):
        with pytest.raises(NatNetParseError):
            scan_frame_of_data(packet(7, data[4:end]), version)


_ORIGIN = (0.0, 0.0, 0.0)
_BODY = RigidBody(1, _ORIGIN, (0.0, 0.0, 0.0, 1.0))
# A frame with ``count`` items of each kind of ITEM_LIMITS, and how many the parsed frame holds
FRAMES_OF = {
    "marker set": (lambda n: FrameOfData(1, marker_sets=(MarkerSet("m"),) * n),
                   lambda f: len(f.marker_sets)),
    "marker set marker": (lambda n: FrameOfData(1, marker_sets=(MarkerSet("m", (_ORIGIN,) * n),)),
                          lambda f: len(f.marker_sets[0].markers)),
    "unlabelled marker": (lambda n: FrameOfData(1, unlabeled_markers=(_ORIGIN,) * n),
                          lambda f: len(f.unlabeled_markers)),
    "rigid body": (lambda n: FrameOfData(1, rigid_bodies=(_BODY,) * n), lambda f: len(f.rigid_bodies)),
    "skeleton": (lambda n: FrameOfData(1, skeletons=(Skeleton(1),) * n), lambda f: len(f.skeletons)),
    "skeleton rigid body": (lambda n: FrameOfData(1, skeletons=(Skeleton(1, (_BODY,) * n),)),
                            lambda f: len(f.skeletons[0].rigid_bodies)),
    "labelled marker": (lambda n: FrameOfData(1, labeled_markers=(LabeledMarker(1, _ORIGIN),) * n),
                        lambda f: len(f.labeled_markers)),
    "force plate": (lambda n: FrameOfData(1, force_plates=(AnalogData(1),) * n),
                    lambda f: len(f.force_plates)),
    "device": (lambda n: FrameOfData(1, devices=(AnalogData(1),) * n), lambda f: len(f.devices)),
    "analog channel": (lambda n: FrameOfData(1, devices=(AnalogData(1, ((),) * n),)),
                       lambda f: len(f.devices[0].channels)),
    "analog sample": (lambda n: FrameOfData(1, devices=(AnalogData(1, ((0.0,) * n,)),)),
                      lambda f: len(f.devices[0].channels[0])),
}


def test_every_item_limit_has_a_frame():
    assert set(FRAMES_OF) == set(ITEM_LIMITS)


@pytest.mark.parametrize("what", sorted(ITEM_LIMITS))
@pytest.mark.parametrize("version", [Version(3, 1), Version(4, 1)], ids=str)
def test_a_frame_beyond_what_motive_sends_is_malformed(what, version):
    """Each item limit of NatNetTypes.h: a frame at the limit is read whole by both readers, one
    item more is refused by both with the cap's message."""
    limit = ITEM_LIMITS[what]
    frame_of, count_of = FRAMES_OF[what]
    at_limit = build_frame_of_data(version, frame_of(limit))
    assert count_of(parse_frame_of_data(at_limit, version)) == limit
    scan_frame_of_data(at_limit, version)
    beyond = build_frame_of_data(version, frame_of(limit + 1))
    for read in (parse_frame_of_data, scan_frame_of_data):
        with pytest.raises(NatNetParseError, match=f"{what} count {limit + 1} is above the {limit} "):
            read(beyond, version)
