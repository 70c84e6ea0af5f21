"""The slave's mailbox (ETG.1000.4) with CoE (ETG.1000.6): SDO upload and download, expedited,
normal and segmented, aborts with CiA 301 codes, emergencies, and the SDO Information service
(object list, object and entry descriptions) through which tools browse the dictionary.

Pure protocol logic: a whole mailbox message in, the messages to send back out; the objects
behind it are an `ObjectAccess` (bytes in their dictionary encoding), so the same server
answers for the device's objects and the EtherCAT communication objects.
"""

import struct
from typing import Protocol

from protocol import cia301
from protocol import ethercat as ec

_U16 = struct.Struct("<H")
_U32 = struct.Struct("<I")
_EMERGENCY = struct.Struct("<HB5s")  # error code, error register, manufacturer data
_MAILBOX_ERROR = struct.Struct("<HH")  # service, detail
# SDO request/response: CoE header + command, index, subindex + 4 data bytes
SDO_FRAME_SIZE = ec.COE_HEADER.size + ec.SDO_HEADER_SIZE + 4


class SdoAbort(Exception):
    """An SDO request refused with a CiA 301 abort code."""

    def __init__(self, code: int):
        super().__init__(f"SDO abort 0x{code:08X}")
        self.code = code


class ObjectAccess(Protocol):
    def upload(self, index: int, subindex: int) -> bytes:
        """The object's value in its dictionary encoding; SdoAbort otherwise."""

    def download(self, index: int, subindex: int, data: bytes) -> None:
        """Store a value given in its dictionary encoding; SdoAbort otherwise."""

    def object_list(self, kind: int) -> list[int]:
        """The indices of list `kind` (`protocol.ethercat.OD_LIST_*`, 1-5), ascending."""

    def object_description(self, index: int) -> tuple[int, int, int, str]:
        """(data type, highest sub-index, object code, name); SdoAbort otherwise."""

    def entry_description(self, index: int, subindex: int) -> tuple[int, int, int, str]:
        """(data type, bit length, object access bits, name); SdoAbort otherwise."""


class CoeMailbox:
    """One slave's mailbox endpoint; `size` is the smaller of its two mailbox buffers."""

    def __init__(self, objects: ObjectAccess, size: int):
        self.objects = objects
        self.size = size
        self.reset()

    def reset(self) -> None:
        """Mailbox (re)started (INIT -> PRE-OP): no transfer under way, counters from 0."""
        self._last_counter = 0
        self._counter = 0
        self._upload: tuple[int, int, bytes, int] | None = None  # index, sub, rest, toggle
        self._download: tuple[int, int, int, bytearray, int] | None = None  # + size, data

    # --- messages ------------------------------------------------------------------------

    def handle(self, message: bytes) -> list[bytes]:
        """Replies to one mailbox message (the whole buffer as the master wrote it)."""
        if len(message) < ec.MAILBOX_HEADER_SIZE:
            return [self._error(ec.MAILBOX_ERROR_SIZE_TOO_SHORT)]
        length, _, _, kind = ec.MAILBOX_HEADER.unpack_from(message, 0)
        body = message[ec.MAILBOX_HEADER_SIZE:ec.MAILBOX_HEADER_SIZE + length]
        if ec.MAILBOX_HEADER_SIZE + length > len(message):
            return [self._error(ec.MAILBOX_ERROR_INVALID_SIZE)]
        counter = (kind >> ec.MAILBOX_COUNTER_SHIFT) & ec.MAILBOX_COUNTER_MASK
        if counter and counter == self._last_counter:
            return []  # the master repeated a message we already handled
        self._last_counter = counter
        if kind & ec.MAILBOX_TYPE_MASK != ec.MAILBOX_TYPE_COE:
            return [self._error(ec.MAILBOX_ERROR_UNSUPPORTED_PROTOCOL)]
        if len(body) < ec.COE_HEADER.size:
            return [self._error(ec.MAILBOX_ERROR_SIZE_TOO_SHORT)]
        (coe,) = ec.COE_HEADER.unpack_from(body, 0)
        if coe >> ec.COE_SERVICE_SHIFT == ec.COE_SDO_INFORMATION:
            return self._sdo_information(bytes(body[ec.COE_HEADER.size:]))
        if coe >> ec.COE_SERVICE_SHIFT != ec.COE_SDO_REQUEST:
            return [self._error(ec.MAILBOX_ERROR_SERVICE_NOT_SUPPORTED)]
        if len(body) < ec.COE_HEADER.size + ec.SDO_HEADER_SIZE:
            return [self._error(ec.MAILBOX_ERROR_SIZE_TOO_SHORT)]
        reply = self._sdo(bytes(body[ec.COE_HEADER.size:]))
        return [reply] if reply is not None else []

    def emergency(self, code: int, register: int, data: bytes = b"") -> bytes:
        """A CoE emergency message (CiA 301 error code and register, 5 manufacturer bytes)."""
        body = _EMERGENCY.pack(code, register, data[:5].ljust(5, b"\x00"))
        return self._message(ec.COE_EMERGENCY << ec.COE_SERVICE_SHIFT, body)

    def _message(self, coe_header: int, body: bytes,
                 kind: int = ec.MAILBOX_TYPE_COE) -> bytes:
        self._counter = self._counter % ec.MAILBOX_COUNTER_MASK + 1
        payload = ec.COE_HEADER.pack(coe_header) + body if kind == ec.MAILBOX_TYPE_COE else body
        return ec.MAILBOX_HEADER.pack(len(payload), 0, 0,
                                      kind | self._counter << ec.MAILBOX_COUNTER_SHIFT) + payload

    def _error(self, detail: int) -> bytes:
        return self._message(0, _MAILBOX_ERROR.pack(ec.MAILBOX_ERROR_SERVICE, detail),
                             kind=ec.MAILBOX_TYPE_ERROR)

    def _response(self, command: int, index: int, subindex: int, data: bytes = b"") -> bytes:
        body = ec.SDO_HEADER.pack(command, index, subindex) + data.ljust(4, b"\x00")
        return self._message(ec.COE_SDO_RESPONSE << ec.COE_SERVICE_SHIFT, body)

    def _abort(self, index: int, subindex: int, code: int) -> bytes:
        self._upload = self._download = None
        body = ec.SDO_HEADER.pack(ec.SDO_CCS_ABORT, index, subindex) + _U32.pack(code)
        return self._message(ec.COE_SDO_REQUEST << ec.COE_SERVICE_SHIFT, body)

    # --- SDO ---------------------------------------------------------------------------

    def _sdo(self, sdo: bytes) -> bytes | None:
        command, index, subindex = ec.SDO_HEADER.unpack_from(sdo, 0)
        specifier = command & ec.SDO_CCS_MASK
        try:
            if specifier == ec.SDO_CCS_UPLOAD:
                return self._upload_initiate(command, index, subindex)
            if specifier == ec.SDO_CCS_UPLOAD_SEGMENT:
                return self._upload_segment(command)
            if specifier == ec.SDO_CCS_DOWNLOAD:
                return self._download_initiate(command, index, subindex, sdo)
            if specifier == ec.SDO_CCS_DOWNLOAD_SEGMENT:
                return self._download_segment(command, sdo)
            if specifier == ec.SDO_CCS_ABORT:
                self._upload = self._download = None
                return None
            raise SdoAbort(cia301.SDO_ABORT_COMMAND)
        except SdoAbort as abort:
            if specifier in (ec.SDO_CCS_UPLOAD_SEGMENT, ec.SDO_CCS_DOWNLOAD_SEGMENT):
                index, subindex = self._transfer_object()
            return self._abort(index, subindex, abort.code)

    def _transfer_object(self) -> tuple[int, int]:
        for transfer in (self._upload, self._download):
            if transfer is not None:
                return transfer[0], transfer[1]
        return 0, 0

    def _upload_initiate(self, command: int, index: int, subindex: int) -> bytes:
        self._upload = None
        if command & ec.SDO_COMPLETE_ACCESS:
            raise SdoAbort(cia301.SDO_ABORT_UNSUPPORTED_ACCESS)
        value = self.objects.upload(index, subindex)
        if 0 < len(value) <= 4:
            flags = ec.SDO_EXPEDITED | ec.SDO_SIZE_INDICATED | (4 - len(value)) << 2
            return self._response(ec.SDO_SCS_UPLOAD | flags, index, subindex, value)
        # normal transfer: size, then as much data as the mailbox holds, then segments
        room = self.size - ec.MAILBOX_HEADER_SIZE - SDO_FRAME_SIZE
        first, rest = value[:room], value[room:]
        if rest:
            self._upload = (index, subindex, rest, 0)
        body = (ec.SDO_HEADER.pack(ec.SDO_SCS_UPLOAD | ec.SDO_SIZE_INDICATED, index, subindex)
                + _U32.pack(len(value)) + first)
        return self._message(ec.COE_SDO_RESPONSE << ec.COE_SERVICE_SHIFT, body)

    def _upload_segment(self, command: int) -> bytes:
        if self._upload is None:
            raise SdoAbort(cia301.SDO_ABORT_COMMAND)
        index, subindex, rest, toggle = self._upload
        if command & ec.SDO_TOGGLE != toggle:
            raise SdoAbort(cia301.SDO_ABORT_TOGGLE)
        room = self.size - ec.MAILBOX_HEADER_SIZE - ec.COE_HEADER.size - 1
        chunk, rest = rest[:room], rest[room:]
        self._upload = (index, subindex, rest, toggle ^ ec.SDO_TOGGLE) if rest else None
        flags = toggle | (0 if rest else ec.SDO_LAST_SEGMENT)
        unused = max(0, ec.SDO_SEGMENT_MIN_DATA - len(chunk))
        body = bytes([ec.SDO_SCS_UPLOAD_SEGMENT | flags | unused << 1]) + chunk + bytes(unused)
        return self._message(ec.COE_SDO_RESPONSE << ec.COE_SERVICE_SHIFT, body)

    def _download_initiate(self, command: int, index: int, subindex: int,
                           sdo: bytes) -> bytes:
        self._download = None
        if command & ec.SDO_COMPLETE_ACCESS:
            raise SdoAbort(cia301.SDO_ABORT_UNSUPPORTED_ACCESS)
        payload = sdo[ec.SDO_HEADER_SIZE:]
        if command & ec.SDO_EXPEDITED:
            size = 4 - (command >> 2 & 0x03) if command & ec.SDO_SIZE_INDICATED else 4
            if len(payload) < size:
                raise SdoAbort(cia301.SDO_ABORT_LENGTH_MISMATCH)
            self.objects.download(index, subindex, bytes(payload[:size]))
            return self._response(ec.SDO_SCS_DOWNLOAD, index, subindex)
        if len(payload) < 4:
            raise SdoAbort(cia301.SDO_ABORT_LENGTH_MISMATCH)
        (size,) = _U32.unpack_from(payload, 0)
        data = bytearray(payload[4:4 + size])
        if len(data) >= size:
            self.objects.download(index, subindex, bytes(data))
        else:
            self._download = (index, subindex, size, data, 0)
        return self._response(ec.SDO_SCS_DOWNLOAD, index, subindex)

    def _download_segment(self, command: int, sdo: bytes) -> bytes:
        if self._download is None:
            raise SdoAbort(cia301.SDO_ABORT_COMMAND)
        index, subindex, size, data, toggle = self._download
        if command & ec.SDO_TOGGLE != toggle:
            raise SdoAbort(cia301.SDO_ABORT_TOGGLE)
        segment = sdo[1:]
        if len(segment) == ec.SDO_SEGMENT_MIN_DATA:
            segment = segment[:ec.SDO_SEGMENT_MIN_DATA - (command >> 1 & 0x07)]
        data += segment
        if len(data) > size:
            raise SdoAbort(cia301.SDO_ABORT_LENGTH_MISMATCH)
        if command & ec.SDO_LAST_SEGMENT:
            self._download = None
            if len(data) != size:
                raise SdoAbort(cia301.SDO_ABORT_LENGTH_MISMATCH)
            self.objects.download(index, subindex, bytes(data))
        else:
            self._download = (index, subindex, size, data, toggle ^ ec.SDO_TOGGLE)
        body = bytes([ec.SDO_SCS_DOWNLOAD_SEGMENT | toggle])
        return self._message(ec.COE_SDO_RESPONSE << ec.COE_SERVICE_SHIFT,
                             body + bytes(ec.SDO_SEGMENT_MIN_DATA))

    # --- SDO Information (ETG.1000.6 5.6.3) -------------------------------------------------

    def _sdo_information(self, info: bytes) -> list[bytes]:
        """A Get OD List, Get Object Description or Get Entry Description request: its
        response (the list in as many fragments as the mailbox needs), or an SDO Information
        error carrying the abort code. Never a mailbox error for a request it understands:
        SOEM 2.0's ecx_mbxreceive retries its read into a buffer it has just released after
        a mailbox error reply and crashes (slaveinfo -map did against this slave)."""
        header = ec.SDO_INFO_HEADER.size
        if len(info) < header:
            return [self._error(ec.MAILBOX_ERROR_SIZE_TOO_SHORT)]
        opcode = info[0] & ec.SDO_INFO_OPCODE_MASK
        data = info[header:]
        try:
            if opcode == ec.SDO_INFO_GET_OD_LIST_REQUEST:
                return self._od_list(data)
            if opcode == ec.SDO_INFO_GET_OBJECT_DESCRIPTION_REQUEST:
                if len(data) < _U16.size:
                    raise SdoAbort(cia301.SDO_ABORT_LENGTH_MISMATCH)
                (index,) = _U16.unpack_from(data, 0)
                data_type, highest, code, name = self.objects.object_description(index)
                body = ec.OBJECT_DESCRIPTION.pack(index, data_type, highest, code)
                return [self._info(ec.SDO_INFO_GET_OBJECT_DESCRIPTION_RESPONSE,
                                   self._with_name(body, name))]
            if opcode == ec.SDO_INFO_GET_ENTRY_DESCRIPTION_REQUEST:
                if len(data) < ec.ENTRY_DESCRIPTION_REQUEST.size:
                    raise SdoAbort(cia301.SDO_ABORT_LENGTH_MISMATCH)
                index, subindex, value_info = ec.ENTRY_DESCRIPTION_REQUEST.unpack_from(data, 0)
                data_type, bits, access, name = self.objects.entry_description(index, subindex)
                # unit, default, minimum and maximum are not given: the reply says so, and a
                # master that asked for none (SOEM) finds the name right after the access
                body = ec.ENTRY_DESCRIPTION.pack(index, subindex,
                                                 value_info & ~ec.ENTRY_VALUE_INFO_OPTIONAL,
                                                 data_type, bits, access)
                return [self._info(ec.SDO_INFO_GET_ENTRY_DESCRIPTION_RESPONSE,
                                   self._with_name(body, name))]
            raise SdoAbort(cia301.SDO_ABORT_COMMAND)
        except SdoAbort as abort:
            return [self._info(ec.SDO_INFO_ERROR, _U32.pack(abort.code))]

    def _od_list(self, data: bytes) -> list[bytes]:
        if len(data) < _U16.size:
            raise SdoAbort(cia301.SDO_ABORT_LENGTH_MISMATCH)
        (kind,) = _U16.unpack_from(data, 0)
        if kind == ec.OD_LIST_LENGTHS:
            values = [len(self.objects.object_list(k)) for k in ec.OD_LISTS]
        elif kind in ec.OD_LISTS:
            values = self.objects.object_list(kind)
        else:
            raise SdoAbort(cia301.SDO_ABORT_VALUE_RANGE)
        payload = _U16.pack(kind) + struct.pack(f"<{len(values)}H", *values)
        # whole 16-bit indices per fragment; the list type only in the first
        room = (self.size - ec.MAILBOX_HEADER_SIZE - ec.COE_HEADER.size
                - ec.SDO_INFO_HEADER.size) & ~1
        chunks = [payload[k:k + room] for k in range(0, len(payload), room)]
        return [self._info(ec.SDO_INFO_GET_OD_LIST_RESPONSE, chunk, len(chunks) - 1 - k)
                for k, chunk in enumerate(chunks)]

    def _with_name(self, body: bytes, name: str) -> bytes:
        """`body` and as much of the name (ASCII) as the mailbox holds (no fragments: SOEM
        reads a description from one message)."""
        room = self.size - ec.MAILBOX_HEADER_SIZE - ec.COE_HEADER.size - ec.SDO_INFO_HEADER.size
        return body + name.encode("ascii", "replace")[:max(0, room - len(body))]

    def _info(self, opcode: int, data: bytes, fragments_left: int = 0) -> bytes:
        flags = ec.SDO_INFO_INCOMPLETE if fragments_left else 0
        body = ec.SDO_INFO_HEADER.pack(opcode | flags, 0, fragments_left) + data
        return self._message(ec.COE_SDO_INFORMATION << ec.COE_SERVICE_SHIFT, body)
