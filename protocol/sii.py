"""The SII EEPROM image (ETG.2010) of a slave, built from its ESI so the two cannot disagree,
and read back into categories for checks.

Layout: words 0-7 ESC configuration area (CRC-8 in word 7), 8-15 identity, 0x18-0x1B standard
mailbox offsets and sizes, 0x1C mailbox protocols, 0x3E size, 0x3F version, then categories
from word 0x40 (type word, length in words, data) up to the end marker 0xFFFF.
"""

import struct

from protocol import ethercat as ec
from protocol.esi import FMMU_USES, EsiDevice, Pdo

SII_VERSION = 1
_GENERAL = struct.Struct("<BBBBBBBBBBBBhBBHH12x")  # 32 bytes (ETG.2010 "General")
_SYNC_MANAGER = struct.Struct("<HHBBBB")
_PDO = struct.Struct("<HBBBBH")
_PDO_ENTRY = struct.Struct("<HBBBBH")
_PDO_MANDATORY, _PDO_DEFAULT, _PDO_FIXED = 0x0001, 0x0002, 0x0010


def build_sii(device: EsiDevice, serial: int = 0) -> bytes:
    """The EEPROM content of `device` (erased words 0xFFFF up to its size)."""
    words = bytearray(0x80)
    config = device.config_data[:ec.SII_CONFIG_BYTES]
    words[:len(config)] = config
    words[ec.SII_WORD_CHECKSUM * 2] = ec.crc8_sii(bytes(words[:ec.SII_CONFIG_BYTES]))
    struct.pack_into("<IIII", words, ec.SII_WORD_VENDOR_ID * 2, device.vendor_id,
                     device.product_code, device.revision, serial)
    mailbox_out = device.sync_manager("MBoxOut")
    mailbox_in = device.sync_manager("MBoxIn")
    struct.pack_into("<HHHH", words, ec.SII_WORD_STANDARD_RX_MAILBOX * 2, mailbox_out.start,
                     mailbox_out.default_size, mailbox_in.start, mailbox_in.default_size)
    protocols = ec.MAILBOX_PROTOCOL_COE if device.coe_details else 0
    struct.pack_into("<H", words, ec.SII_WORD_MAILBOX_PROTOCOL * 2, protocols)
    struct.pack_into("<HH", words, ec.SII_WORD_SIZE * 2, device.eeprom_bytes * 8 // 1024 - 1,
                     SII_VERSION)

    strings = [device.name, device.type_name, device.group]
    image = bytes(words)
    image += _category(ec.SII_CATEGORY_STRINGS, _strings(strings))
    image += _category(ec.SII_CATEGORY_GENERAL, _general(device, name=1, order=2, group=3))
    image += _category(ec.SII_CATEGORY_FMMU, bytes(
        FMMU_USES[use] for use in device.fmmus))
    image += _category(ec.SII_CATEGORY_SYNC_MANAGER, b"".join(
        _SYNC_MANAGER.pack(sm.start, _sm_length(device, n), sm.control, 0,
                           int(sm.enable), sm.sm_type)
        for n, sm in enumerate(device.sync_managers)))
    image += _category(ec.SII_CATEGORY_TXPDO, b"".join(_pdo(p) for p in device.txpdos))
    image += _category(ec.SII_CATEGORY_RXPDO, b"".join(_pdo(p) for p in device.rxpdos))
    image += struct.pack("<H", ec.SII_CATEGORY_END)
    if len(image) > device.eeprom_bytes:
        raise ValueError(f"SII image of {len(image)} bytes exceeds the ESI's EEPROM size of "
                         f"{device.eeprom_bytes} bytes")
    return image + b"\xff" * (device.eeprom_bytes - len(image))


def _category(kind: int, data: bytes) -> bytes:
    if len(data) % 2:
        data += b"\x00"
    return struct.pack("<HH", kind, len(data) // 2) + data


def _strings(strings: list[str]) -> bytes:
    out = bytearray([len(strings)])
    for text in strings:
        raw = text.encode("ascii", "replace")[:255]
        out += bytes([len(raw)]) + raw
    return bytes(out)


def _general(device: EsiDevice, name: int, order: int, group: int) -> bytes:
    # Physics "YY": ports 0 and 1 are MII; nibble per port in PhysicalPort
    return _GENERAL.pack(group, 0, order, name, 0, device.coe_details, 0, 0, 0, 0, 0, 0,
                         0, group, 0, 0x0011, 0)


def _sm_length(device: EsiDevice, number: int) -> int:
    sm = device.sync_managers[number]
    if sm.sm_type in (ec.SM_TYPE_MAILBOX_OUT, ec.SM_TYPE_MAILBOX_IN):
        return sm.default_size
    return device.pdo_bytes(number)


def _pdo(pdo: Pdo) -> bytes:
    flags = (_PDO_MANDATORY if pdo.mandatory else 0) | _PDO_DEFAULT | (
        _PDO_FIXED if pdo.fixed else 0)
    out = _PDO.pack(pdo.index, len(pdo.entries), pdo.sync_manager, 0, 0, flags)
    for entry in pdo.entries:
        out += _PDO_ENTRY.pack(entry.index, entry.subindex, 0, entry.data_type, entry.bits, 0)
    return out


# --- reading an image back ---------------------------------------------------------------------

def categories(image: bytes) -> dict[int, bytes]:
    """Category type -> data, walking from word 0x40 to the end marker. ValueError when the
    chain runs off the image."""
    out = {}
    offset = ec.SII_FIRST_CATEGORY * 2
    while True:
        if offset + 2 > len(image):
            raise ValueError("SII category chain runs past the image (no end marker)")
        (kind,) = struct.unpack_from("<H", image, offset)
        if kind == ec.SII_CATEGORY_END:
            return out
        if offset + 4 > len(image):
            raise ValueError(f"SII category {kind} header cut at byte {offset}")
        (words,) = struct.unpack_from("<H", image, offset + 2)
        start, end = offset + 4, offset + 4 + 2 * words
        if end > len(image):
            raise ValueError(f"SII category {kind} runs past the image")
        out[kind] = image[start:end]
        offset = end


def identity(image: bytes) -> tuple[int, int, int, int]:
    """(vendor id, product code, revision, serial) from words 8-15."""
    return struct.unpack_from("<IIII", image, ec.SII_WORD_VENDOR_ID * 2)


def strings(image: bytes) -> list[str]:
    data = categories(image)[ec.SII_CATEGORY_STRINGS]
    out, offset = [], 1
    for _ in range(data[0]):
        length = data[offset]
        out.append(data[offset + 1:offset + 1 + length].decode("ascii"))
        offset += 1 + length
    return out


def sync_managers(image: bytes) -> list[tuple[int, int, int, int, int]]:
    """(start, length, control, enable, type) per sync manager of the SM category."""
    data = categories(image)[ec.SII_CATEGORY_SYNC_MANAGER]
    return [(start, length, control, enable, kind) for start, length, control, _, enable, kind
            in _SYNC_MANAGER.iter_unpack(data)]


def pdo_entries(image: bytes, category: int) -> list[tuple[int, int, list[int]]]:
    """(PDO index, sync manager, mapping entries) per PDO of a TXPDO/RXPDO category."""
    data = categories(image)[category]
    out, offset = [], 0
    while offset + _PDO.size <= len(data):
        index, count, sm, _, _, _ = _PDO.unpack_from(data, offset)
        offset += _PDO.size
        entries = []
        for _ in range(count):
            e_index, e_sub, _, _, bits, _ = _PDO_ENTRY.unpack_from(data, offset)
            entries.append(e_index << 16 | e_sub << 8 | bits)
            offset += _PDO_ENTRY.size
        out.append((index, sm, entries))
    return out
