"""The slave's CoE mailbox server message by message (expedited, normal and segmented SDO in
both directions, aborts, mailbox errors, emergencies, the SDO Information service), its object
rules (PDO assignment and
mapping only in PRE-OP, only what the ESI offers), and the ESI, SII and EDS agreeing."""

import itertools
import struct

import pytest

from model.parameters import load_model
from protocol import cia301, eds_path, esi, esi_path, objects, sii
from protocol import ethercat as ec
from protocol.dictionary import load_dictionary, variable
from protocol.esi import EsiError, ethercat_dictionary, load_esi, parse_esi
from sim_bus.device import Cia402Device
from sim_bus.ethercat.mailbox import CoeMailbox, SdoAbort
from sim_bus.ethercat.objects import CoeObjects

ESI = load_esi(esi_path())
SIZE = 128


class Store:
    """Objects as bytes, for the protocol alone."""

    def __init__(self):
        self.values = {(0x1008, 0): b"Virtual elbow drive, " * 20, (0x6040, 0): b"\x00\x00"}

    def upload(self, index, subindex):
        if (index, subindex) not in self.values:
            raise SdoAbort(cia301.SDO_ABORT_NOT_IN_DICTIONARY)
        return self.values[(index, subindex)]

    def download(self, index, subindex, data):
        if (index, subindex) == (0x6040, 0) and len(data) != 2:
            raise SdoAbort(cia301.SDO_ABORT_LENGTH_MISMATCH)
        self.values[(index, subindex)] = data


class Client:
    """A CoE SDO client shaped like SOEM's ecx_SDOread / ecx_SDOwrite."""

    def __init__(self, server: CoeMailbox):
        self.server = server
        self.counter = 0

    def request(self, sdo: bytes, service: int = ec.COE_SDO_REQUEST) -> list[bytes]:
        self.counter = self.counter % 7 + 1
        body = ec.COE_HEADER.pack(service << ec.COE_SERVICE_SHIFT) + sdo
        message = ec.MAILBOX_HEADER.pack(len(body), 0, 0, ec.MAILBOX_TYPE_COE
                                         | self.counter << 4) + body
        return self.server.handle(message.ljust(SIZE, b"\x00"))

    def one(self, sdo: bytes) -> tuple[int, bytes]:
        [reply] = self.request(sdo)
        length, _, _, kind = ec.MAILBOX_HEADER.unpack_from(reply)
        assert kind & 0x0F == ec.MAILBOX_TYPE_COE and len(reply) == 6 + length <= SIZE
        return ec.COE_HEADER.unpack_from(reply, 6)[0] >> 12, reply[8:6 + length]

    def upload(self, index: int, subindex: int) -> bytes:
        service, sdo = self.one(ec.SDO_HEADER.pack(0x40, index, subindex) + bytes(4))
        command = sdo[0]
        if command == ec.SDO_CCS_ABORT:
            raise SdoAbort(struct.unpack_from("<I", sdo, 4)[0])
        assert service == ec.COE_SDO_RESPONSE
        if command & ec.SDO_EXPEDITED:
            return sdo[4:8 - (command >> 2 & 3)]
        (size,) = struct.unpack_from("<I", sdo, 4)
        data, toggle = bytearray(sdo[8:]), 0
        while len(data) < size:
            _, segment = self.one(bytes([0x60 | toggle]) + bytes(7))
            assert segment[0] & ec.SDO_TOGGLE == toggle
            chunk = segment[1:]
            if segment[0] & 1 and len(chunk) == 7:
                chunk = chunk[:7 - (segment[0] >> 1 & 7)]
            data += chunk
            toggle ^= 0x10
            if segment[0] & 1:
                break
        return bytes(data)

    def download(self, index: int, subindex: int, data: bytes) -> None:
        if len(data) <= 4:
            command = 0x23 | (4 - len(data)) << 2
            replies = [self.one(ec.SDO_HEADER.pack(command, index, subindex)
                                + data.ljust(4, b"\x00"))]
        else:
            room = SIZE - 16
            replies = [self.one(ec.SDO_HEADER.pack(0x21, index, subindex)
                                + struct.pack("<I", len(data)) + data[:room])]
            rest, toggle = data[room:], 0
            while rest:
                chunk, rest = rest[:room + 7], rest[room + 7:]
                command = toggle | (0 if rest else 1)
                if not rest and len(chunk) < 7:
                    command |= (7 - len(chunk)) << 1
                    chunk = chunk.ljust(7, b"\x00")
                replies.append(self.one(bytes([command]) + chunk))
                toggle ^= 0x10
        for _, sdo in replies:
            if sdo[0] == ec.SDO_CCS_ABORT:
                raise SdoAbort(struct.unpack_from("<I", sdo, 4)[0])


def test_expedited_upload_and_download():
    client = Client(CoeMailbox(Store(), SIZE))
    client.download(0x6040, 0, b"\x0f\x00")
    assert client.upload(0x6040, 0) == b"\x0f\x00"


def test_segmented_upload_and_download_move_more_than_a_mailbox():
    store = Store()
    client = Client(CoeMailbox(store, SIZE))
    assert client.upload(0x1008, 0) == store.values[(0x1008, 0)]
    for size in (5, SIZE - 16, SIZE - 15, 3 * SIZE + 1):
        data = bytes(k % 251 for k in range(size))
        client.download(0x1008, 0, data)
        assert store.values[(0x1008, 0)] == data


def test_aborts_carry_the_code_and_end_a_transfer():
    client = Client(CoeMailbox(Store(), SIZE))
    with pytest.raises(SdoAbort) as abort:
        client.upload(0x5555, 0)
    assert abort.value.code == cia301.SDO_ABORT_NOT_IN_DICTIONARY
    with pytest.raises(SdoAbort) as abort:
        client.download(0x6040, 0, b"\x01")
    assert abort.value.code == cia301.SDO_ABORT_LENGTH_MISMATCH
    _, sdo = client.one(bytes([0x60]) + bytes(7))  # a segment without a transfer
    assert sdo[0] == ec.SDO_CCS_ABORT
    assert struct.unpack_from("<I", sdo, 4)[0] == cia301.SDO_ABORT_COMMAND
    _, sdo = client.one(ec.SDO_HEADER.pack(0x50, 0x6040, 0) + bytes(4))  # complete access
    assert struct.unpack_from("<I", sdo, 4)[0] == cia301.SDO_ABORT_UNSUPPORTED_ACCESS


def test_toggle_error_aborts_a_segmented_upload():
    client = Client(CoeMailbox(Store(), SIZE))
    client.one(ec.SDO_HEADER.pack(0x40, 0x1008, 0) + bytes(4))
    _, sdo = client.one(bytes([0x70]) + bytes(7))  # toggle 1 first: wrong
    assert sdo[0] == ec.SDO_CCS_ABORT
    assert struct.unpack_from("<HBI", sdo, 1) == (0x1008, 0, cia301.SDO_ABORT_TOGGLE)


def test_mailbox_errors_and_repeated_messages():
    server = CoeMailbox(Store(), SIZE)
    client = Client(server)
    [reply] = client.request(b"\x00" * 8, service=0x06)  # RxPDO remote request: not offered
    assert reply[5] & 0x0F == ec.MAILBOX_TYPE_ERROR
    assert struct.unpack_from("<HH", reply, 6) == (1, ec.MAILBOX_ERROR_SERVICE_NOT_SUPPORTED)
    other = ec.MAILBOX_HEADER.pack(4, 0, 0, 0x04 | 2 << 4) + bytes(4)  # FoE
    [reply] = server.handle(other.ljust(SIZE, b"\x00"))
    assert struct.unpack_from("<H", reply, 8)[0] == ec.MAILBOX_ERROR_UNSUPPORTED_PROTOCOL
    assert server.handle(other.ljust(SIZE, b"\x00")) == []  # same counter: a repeat, ignored
    [reply] = server.handle(ec.MAILBOX_HEADER.pack(500, 0, 0, 0x03 | 3 << 4).ljust(SIZE, b"\0"))
    assert struct.unpack_from("<H", reply, 8)[0] == ec.MAILBOX_ERROR_INVALID_SIZE


def test_emergency_message_layout():
    message = CoeMailbox(Store(), SIZE).emergency(0x2310, 0x02)
    length, _, _, kind = ec.MAILBOX_HEADER.unpack_from(message)
    assert (length, kind & 0x0F) == (10, ec.MAILBOX_TYPE_COE)
    assert struct.unpack_from("<HHB", message, 6) == (ec.COE_EMERGENCY << 12, 0x2310, 0x02)


@pytest.fixture
def coe():
    objects_ = CoeObjects(Cia402Device(load_model()), ESI)
    objects_.pdo_config_allowed = True
    return objects_


def test_communication_objects_follow_the_esi(coe):
    assert coe.upload(ec.SM_COMMUNICATION_TYPE, 0) == b"\x04"
    assert [coe.upload(ec.SM_COMMUNICATION_TYPE, k)[0] for k in (1, 2, 3, 4)] == [1, 2, 3, 4]
    assert coe.assigned(ec.RXPDO_ASSIGN) == [0x1600]
    assert coe.assigned_entries(ec.TXPDO_ASSIGN) == [e.mapping_entry
                                                     for e in ESI.txpdos[0].entries]
    with pytest.raises(SdoAbort) as abort:
        coe.upload(0x1800, 1)  # CANopen TPDO COB-ID: no such thing on EtherCAT
    assert abort.value.code == cia301.SDO_ABORT_NOT_IN_DICTIONARY


def test_pdo_assignment_rules(coe):
    with pytest.raises(SdoAbort) as abort:
        coe.download(ec.RXPDO_ASSIGN, 1, b"\x00\x16")  # sub-index 0 is still 1
    assert abort.value.code == ec.SDO_ABORT_SUBINDEX_ZERO_NOT_ZERO
    coe.download(ec.RXPDO_ASSIGN, 0, b"\x00")
    with pytest.raises(SdoAbort):
        coe.download(ec.RXPDO_ASSIGN, 1, b"\x00\x1a")  # a TxPDO into the RxPDO assignment
    coe.download(ec.RXPDO_ASSIGN, 1, b"\x00\x16")
    coe.download(ec.RXPDO_ASSIGN, 0, b"\x01")
    assert coe.assigned(ec.RXPDO_ASSIGN) == [0x1600]
    coe.pdo_config_allowed = False  # SAFE-OP, OP
    with pytest.raises(SdoAbort) as abort:
        coe.download(ec.RXPDO_ASSIGN, 0, b"\x00")
    assert abort.value.code == cia301.SDO_ABORT_WRONG_STATE


def test_what_the_outputs_carry_is_written_by_sdo_in_pre_op_only(coe):
    """From SAFE-OP on the process data owns the objects an assigned RxPDO maps: an SDO write
    to one (the controlword) is refused, as drives in the field refuse it; the others, and
    every read, still go."""
    carried = {e.index for e in ESI.rxpdos[0].entries}
    assert objects.CONTROLWORD in carried and objects.MODES_OF_OPERATION not in carried
    coe.download(objects.CONTROLWORD, 0, b"\x06\x00")  # PRE-OP
    coe.pdo_config_allowed = False  # SAFE-OP, OP
    with pytest.raises(SdoAbort) as abort:
        coe.download(objects.CONTROLWORD, 0, b"\x0f\x00")
    assert abort.value.code == cia301.SDO_ABORT_WRONG_STATE
    assert coe.upload(objects.CONTROLWORD, 0) == b"\x06\x00"
    coe.download(objects.MODES_OF_OPERATION, 0, b"\x0a")
    assert coe.upload(objects.MODES_OF_OPERATION, 0) == b"\x0a"


def test_pdo_mapping_takes_only_what_the_esi_offers_in_the_right_direction(coe):
    coe.download(0x1600, 0, b"\x00")

    def entry(index, bits):
        return struct.pack("<I", index << 16 | bits)

    for index, bits in ((objects.TARGET_CURRENT, 32), (objects.STATUSWORD, 16)):
        with pytest.raises(SdoAbort) as abort:
            coe.download(0x1600, 1, entry(index, bits))
        assert abort.value.code == cia301.SDO_ABORT_NOT_MAPPABLE
    coe.download(0x1600, 1, entry(objects.TARGET_TORQUE, 16))
    with pytest.raises(SdoAbort):
        coe.download(0x1600, 0, b"\x03")  # entry 3 is empty
    coe.download(0x1600, 0, b"\x01")
    assert coe.assigned_entries(ec.RXPDO_ASSIGN) == [objects.TARGET_TORQUE << 16 | 16]


def test_esi_sii_and_eds_agree():
    image = sii.build_sii(ESI)
    assert sii.identity(image)[:3] == ESI.identity
    dictionary = load_dictionary(eds_path())
    assert tuple(variable(dictionary, 0x1018, k).default for k in (1, 2, 3)) == ESI.identity
    assert image[ec.SII_WORD_CHECKSUM * 2] == ec.crc8_sii(image[:ec.SII_CONFIG_BYTES])
    assert sii.strings(image)[0] == ESI.name
    mailbox = struct.unpack_from("<HHHH", image, ec.SII_WORD_STANDARD_RX_MAILBOX * 2)
    assert mailbox == (0x1000, 128, 0x1080, 128)
    assert sii.sync_managers(image) == [(0x1000, 128, 0x26, 1, 1), (0x1080, 128, 0x22, 1, 2),
                                        (0x1100, 4, 0x64, 1, 3), (0x1180, 18, 0x20, 1, 4)]
    assert sii.pdo_entries(image, ec.SII_CATEGORY_RXPDO) == [
        (0x1600, 2, [0x60400010, 0x60710010])]
    assert sii.pdo_entries(image, ec.SII_CATEGORY_TXPDO) == [
        (0x1A00, 3, [e.mapping_entry for e in ESI.txpdos[0].entries])]
    for pdo in ESI.rxpdos + ESI.txpdos:  # every ESI entry is the EDS's object, same size
        for entry in pdo.entries:
            var = variable(dictionary, entry.index, entry.subindex)
            assert var.pdo_mappable and len(var) == entry.bits and var.data_type == (
                entry.data_type)
    seen = ethercat_dictionary(dictionary, ESI)
    assert not variable(seen, objects.TARGET_CURRENT).pdo_mappable
    assert variable(seen, objects.TARGET_TORQUE).pdo_mappable


@pytest.mark.parametrize("text,message", [
    ("<nope/>", "expected <EtherCATInfo>"),
    ("not xml", "not XML"),
    ("<EtherCATInfo><Vendor><Id>#xZZ</Id><Name>x</Name></Vendor><Descriptions><Devices><Device>"
     "<Type ProductCode='1' RevisionNo='1'>t</Type><Name>n</Name><GroupType>g</GroupType>"
     "</Device></Devices></Descriptions></EtherCATInfo>", "Vendor/Id: '#xZZ' is not a number"),
])
def test_bad_esi_is_named(text, message):
    with pytest.raises(EsiError, match=message):
        parse_esi(text)


# --- SDO Information (ETG.1000.6 5.6.3) ---------------------------------------------------------

_counters = itertools.cycle(range(1, 8))


def info(server: CoeMailbox, opcode: int, data: bytes) -> list[tuple[int, int, bytes]]:
    """One SDO Information request: each reply's (opcode byte, fragments left, data), every
    reply a whole CoE message no longer than the mailbox."""
    body = ec.COE_HEADER.pack(ec.COE_SDO_INFORMATION << 12) + ec.SDO_INFO_HEADER.pack(
        opcode, 0, 0) + data
    message = ec.MAILBOX_HEADER.pack(len(body), 0, 0, ec.MAILBOX_TYPE_COE
                                     | next(_counters) << 4) + body
    out = []
    for reply in server.handle(message.ljust(server.size, b"\x00")):
        length, _, _, kind = ec.MAILBOX_HEADER.unpack_from(reply)
        assert kind & 0x0F == ec.MAILBOX_TYPE_COE and len(reply) == 6 + length <= server.size
        assert ec.COE_HEADER.unpack_from(reply, 6)[0] >> 12 == ec.COE_SDO_INFORMATION
        code, _, left = ec.SDO_INFO_HEADER.unpack_from(reply, 8)
        out.append((code, left, reply[12:6 + length]))
    return out


@pytest.fixture
def browser():
    return CoeMailbox(CoeObjects(Cia402Device(load_model()), ESI), SIZE)


def test_the_object_list_comes_in_fragments_that_count_down(browser):
    whole = info(browser, ec.SDO_INFO_GET_OD_LIST_REQUEST, struct.pack("<H", ec.OD_LIST_ALL))
    browser.size = 48  # a slave with a small mailbox: 18 indices a message at most
    replies = info(browser, ec.SDO_INFO_GET_OD_LIST_REQUEST, struct.pack("<H", ec.OD_LIST_ALL))
    assert len(whole) == 1 and len(replies) > 2
    assert [left for _, left, _ in replies] == list(range(len(replies) - 1, -1, -1))
    assert [code for code, _, _ in replies] == (
        [ec.SDO_INFO_GET_OD_LIST_RESPONSE | ec.SDO_INFO_INCOMPLETE] * (len(replies) - 1)
        + [ec.SDO_INFO_GET_OD_LIST_RESPONSE])
    data = b"".join(chunk for _, _, chunk in replies)
    kind, *indices = struct.unpack(f"<{len(data) // 2}H", data)
    assert kind == ec.OD_LIST_ALL and indices == sorted(indices)
    dictionary = load_dictionary(eds_path())
    # the EDS's objects and the EtherCAT communication objects, not CANopen's PDO COB-IDs
    assert {0x1000, 0x1018, 0x1600, 0x1A00, 0x6041, 0x6071} <= set(indices)
    assert {ec.SM_COMMUNICATION_TYPE, ec.RXPDO_ASSIGN, ec.TXPDO_ASSIGN,
            esi.ERROR_SETTINGS} <= set(indices)
    assert not {0x1400, 0x1800} & set(indices)
    assert len(indices) == len([i for i in dictionary if not 0x1400 <= i < 0x1600
                                and not 0x1800 <= i < 0x1A00]) + 4
    assert whole[0][2] == data
    [(_, _, lengths)] = info(browser, ec.SDO_INFO_GET_OD_LIST_REQUEST,
                             struct.pack("<H", ec.OD_LIST_LENGTHS))
    counts = struct.unpack("<H5H", lengths)[1:]
    assert counts[0] == len(indices)
    [(_, _, tx)] = info(browser, ec.SDO_INFO_GET_OD_LIST_REQUEST,
                        struct.pack("<H", ec.OD_LIST_TXPDO_MAPPABLE))
    assert set(struct.unpack(f"<{len(tx) // 2}H", tx)[1:]) == {
        e.index for e in ESI.txpdos[0].entries}
    assert counts[2] == len(tx) // 2 - 1


def test_object_and_entry_descriptions_follow_the_eds_and_the_esi(browser):
    [(code, _, data)] = info(browser, ec.SDO_INFO_GET_OBJECT_DESCRIPTION_REQUEST,
                             struct.pack("<H", objects.STATUSWORD))
    assert code == ec.SDO_INFO_GET_OBJECT_DESCRIPTION_RESPONSE
    assert ec.OBJECT_DESCRIPTION.unpack_from(data) == (objects.STATUSWORD, 0x0006, 0,
                                                       ec.OBJECT_CODE_VAR)
    assert data[6:] == b"Statusword"
    [(_, _, data)] = info(browser, ec.SDO_INFO_GET_OBJECT_DESCRIPTION_REQUEST,
                          struct.pack("<H", ec.RXPDO_ASSIGN))
    assert ec.OBJECT_DESCRIPTION.unpack_from(data)[1:] == (0x0006, 1, ec.OBJECT_CODE_ARRAY)
    [(code, _, data)] = info(browser, ec.SDO_INFO_GET_ENTRY_DESCRIPTION_REQUEST,
                             ec.ENTRY_DESCRIPTION_REQUEST.pack(objects.STATUSWORD, 0, 0x7F))
    assert code == ec.SDO_INFO_GET_ENTRY_DESCRIPTION_RESPONSE
    index, sub, value_info, data_type, bits, access = ec.ENTRY_DESCRIPTION.unpack_from(data)
    # no unit, default, minimum or maximum follow: the name comes right after the access
    assert (index, sub, value_info, data_type, bits) == (objects.STATUSWORD, 0, 0x07, 6, 16)
    assert access == ec.ENTRY_ACCESS_READ | ec.ENTRY_ACCESS_TXPDO
    assert data[ec.ENTRY_DESCRIPTION.size:] == b"Statusword"
    [(_, _, data)] = info(browser, ec.SDO_INFO_GET_ENTRY_DESCRIPTION_REQUEST,
                          ec.ENTRY_DESCRIPTION_REQUEST.pack(objects.TARGET_TORQUE, 0, 7))
    assert ec.ENTRY_DESCRIPTION.unpack_from(data)[5] == (
        ec.ENTRY_ACCESS_READ | ec.ENTRY_ACCESS_WRITE | ec.ENTRY_ACCESS_RXPDO)
    [(_, _, data)] = info(browser, ec.SDO_INFO_GET_ENTRY_DESCRIPTION_REQUEST,
                          ec.ENTRY_DESCRIPTION_REQUEST.pack(0x1A00, 1, 7))
    assert ec.ENTRY_DESCRIPTION.unpack_from(data)[3:] == (7, 32, ec.ENTRY_ACCESS_READ | 0x08)


@pytest.mark.parametrize("opcode, data, abort", [
    (ec.SDO_INFO_GET_OBJECT_DESCRIPTION_REQUEST, struct.pack("<H", 0x5555),
     cia301.SDO_ABORT_NOT_IN_DICTIONARY),
    (ec.SDO_INFO_GET_OBJECT_DESCRIPTION_REQUEST, struct.pack("<H", 0x1800),
     cia301.SDO_ABORT_NOT_IN_DICTIONARY),
    (ec.SDO_INFO_GET_ENTRY_DESCRIPTION_REQUEST, ec.ENTRY_DESCRIPTION_REQUEST.pack(0x6041, 1, 7),
     cia301.SDO_ABORT_NO_SUBINDEX),
    (ec.SDO_INFO_GET_OD_LIST_REQUEST, struct.pack("<H", 9), cia301.SDO_ABORT_VALUE_RANGE),
    (ec.SDO_INFO_GET_OD_LIST_REQUEST, b"", cia301.SDO_ABORT_LENGTH_MISMATCH),
    (0x09, b"", cia301.SDO_ABORT_COMMAND),
])
def test_a_request_it_cannot_answer_gets_an_sdo_information_error(browser, opcode, data, abort):
    """Never a mailbox error (SOEM 2.0 crashes reading one in the middle of its receive)."""
    [(code, left, reply)] = info(browser, opcode, data)
    assert (code, left) == (ec.SDO_INFO_ERROR, 0)
    assert struct.unpack("<I", reply) == (abort,)
