"""Scene uploads: a scene file with its meshes, sent as one archive (.zip, .tar.gz) or as
several files, unpacked into a private temporary folder that the scene is then read from.

Limits apply to what is unpacked twice: every member's declared size is checked against
what the limit leaves before the member is read (a tar header's before tarfile reads
what it declares: a pax or GNU long-name header's content is read whole, into memory), and
the bytes are counted in chunks as they are written, so a header that lies stops at the
limit too. Every name must stay inside the folder: no absolute paths, no `..`, no links or
devices. Archives inside an archive are stored, not unpacked."""

from __future__ import annotations

import gzip
import lzma
import stat
import tarfile
import zipfile
import zlib
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import IO, BinaryIO, Self

MAX_UPLOAD_BYTES = 128 * 1024 * 1024  # unpacked, all files together
MAX_UPLOAD_FILES = 256  # entries unpacked (folders count)
MAX_NAME_CHARS = 1024  # a path inside the upload
MAX_PART_CHARS = 255  # one folder or file name
# A tar metadata header's content (pax attributes, a GNU long name): names and attributes
# take far less; tarfile reads such a content whole.
MAX_TAR_HEADER_BYTES = 1 << 20
TAR_METADATA_TYPES = frozenset({tarfile.XHDTYPE, tarfile.XGLTYPE, tarfile.SOLARIS_XHDTYPE, tarfile.GNUTYPE_LONGNAME,
                                tarfile.GNUTYPE_LONGLINK})
CHUNK = 1 << 16
ZIP_SUFFIXES = (".zip",)
TAR_SUFFIXES = (".tar.gz", ".tgz", ".tar")
SCENE_SUFFIXES = (".json", ".xml")


class UploadError(ValueError):
    """An upload refused: `field` is the form field, `status` 422 or 413 (too large)."""

    def __init__(self, field: str, message: str, status: int = 422) -> None:
        super().__init__(f"{field}: {message}")
        self.field = field
        self.message = message
        self.status = status


def relative_name(field: str, name: str) -> PurePosixPath:
    """A name inside the upload, or UploadError: never absolute, never `..`, no NUL or backslash."""
    if not name or len(name) > MAX_NAME_CHARS or "\x00" in name or "\\" in name:
        raise UploadError(field, f"bad file name {name[:80]!r}")
    path = PurePosixPath(name)
    if path.is_absolute() or ".." in path.parts:
        raise UploadError(field, f"path {name[:80]!r} lies outside the upload")
    parts = [p for p in path.parts if p != "."]
    if not parts or any(len(p) > MAX_PART_CHARS for p in parts):
        raise UploadError(field, f"bad file name {name[:80]!r}")
    return PurePosixPath(*parts)


class _Declared(Exception):
    """A tar header that declares more than the limits allow (raised inside tarfile, which
    knows no form field)."""

    def __init__(self, name: str, size: int, limit: int) -> None:
        super().__init__(name, size, limit)
        self.name, self.size, self.limit = name, size, limit


class _CheckedTarInfo(tarfile.TarInfo):
    """A tar header checked as tarfile parses it, before tarfile reads what it declares."""

    @classmethod
    def frombuf(cls, buf: bytes | bytearray, encoding: str, errors: str) -> Self:
        info = super().frombuf(buf, encoding, errors)
        limit = MAX_TAR_HEADER_BYTES if info.type in TAR_METADATA_TYPES else MAX_UPLOAD_BYTES
        if info.size > limit:
            raise _Declared(info.name, info.size, limit)
        return info


Source = IO[bytes]  # a readable binary stream: an upload, an archive member (`Unpacker.bytes` shadows `bytes`)


@dataclass
class Unpacker:
    """Writes files into `root` while counting entries and bytes against the limits."""

    root: Path
    entries: int = 0
    bytes: int = 0

    def _count_entry(self, field: str) -> None:
        self.entries += 1
        if self.entries > MAX_UPLOAD_FILES:
            raise UploadError(field, f"more than {MAX_UPLOAD_FILES} files", 413)

    def _make_folder(self, field: str, name: str, folder: PurePosixPath) -> None:
        """`folder` (relative) and the folders above it; a file already on the way is a clash."""
        path = self.root
        for part in folder.parts:
            path = path / part
            if path.is_file():
                clash = path.relative_to(self.root).as_posix()
                raise UploadError(field, f"{name[:80]!r}: {clash[:80]!r} is both a file and a folder in the upload")
            path.mkdir(exist_ok=True)

    def folder(self, field: str, name: str) -> None:
        self._count_entry(field)
        if name and not PurePosixPath(name).parts:  # "./", the archive's own top (tar -C DIR .)
            return
        self._make_folder(field, name, relative_name(field, name))

    def declared(self, field: str, name: str, size: int) -> None:
        """A member's declared size against what the limit leaves, before it is read."""
        if self.bytes + size > MAX_UPLOAD_BYTES:
            raise UploadError(field, f"{name[:80]!r} declares {size} bytes: the unpacked upload would be larger "
                                     f"than {MAX_UPLOAD_BYTES} bytes", 413)

    def write(self, field: str, name: str, source: Source) -> None:
        """One file, copied in chunks; refused past the byte limit or if the name is taken."""
        self._count_entry(field)
        relative = relative_name(field, name)
        self._make_folder(field, name, relative.parent)
        target = self.root / relative
        try:
            out = target.open("xb")
        except (FileExistsError, IsADirectoryError):
            if target.is_dir():
                raise UploadError(field, f"{name[:80]!r}: {relative.as_posix()[:80]!r} is both a file and a folder "
                                         "in the upload") from None
            raise UploadError(field, f"{name[:80]!r} appears twice in the upload") from None
        with out:
            while chunk := source.read(CHUNK):
                self.bytes += len(chunk)
                if self.bytes > MAX_UPLOAD_BYTES:
                    raise UploadError(field, f"{name[:80]!r}: the unpacked upload is larger than {MAX_UPLOAD_BYTES} "
                                             "bytes", 413)
                out.write(chunk)

    def unpack(self, field: str, name: str, source: BinaryIO) -> None:
        """An archive, by the suffix of its name, unpacked into the root."""
        lower = name.lower()
        try:
            if lower.endswith(ZIP_SUFFIXES):
                self._zip(field, source)
            elif lower.endswith(TAR_SUFFIXES):
                self._tar(field, source)
            else:
                raise UploadError(field, f"{name[:80]!r}: an archive is a .zip, .tar.gz, .tgz or .tar file")
        except (zipfile.BadZipFile, zipfile.LargeZipFile, tarfile.TarError, zlib.error, gzip.BadGzipFile,
                lzma.LZMAError, EOFError, NotImplementedError, RuntimeError) as exc:  # RuntimeError: encrypted zip
            raise UploadError(field, f"{name[:80]!r} is not a readable archive: {exc}") from None

    def _zip(self, field: str, source: BinaryIO) -> None:
        with zipfile.ZipFile(source) as archive:
            members = archive.infolist()
            if self.entries + len(members) > MAX_UPLOAD_FILES:
                raise UploadError(field, f"{len(members)} entries: more than {MAX_UPLOAD_FILES} files", 413)
            for info in members:
                if stat.S_ISLNK(info.external_attr >> 16):
                    raise UploadError(field, f"{info.filename[:80]!r} is a link: links are refused")
                if info.is_dir():
                    self.folder(field, info.filename)
                    continue
                self.declared(field, info.filename, info.file_size)
                with archive.open(info) as member:
                    self.write(field, info.filename, member)

    def _tar(self, field: str, source: BinaryIO) -> None:
        try:
            self._tar_members(field, source)
        except _Declared as exc:
            raise UploadError(field, f"{exc.name[:80]!r}: a tar header declares {exc.size} bytes, more than the "
                                     f"{exc.limit} bytes the limits allow", 413) from None

    def _tar_members(self, field: str, source: BinaryIO) -> None:
        with tarfile.open(fileobj=source, mode="r:*", tarinfo=_CheckedTarInfo) as archive:
            for member in archive:  # streamed: one member at a time
                if member.isdir():
                    self.folder(field, member.name)
                elif member.isfile():
                    self.declared(field, member.name, member.size)  # its pax size included
                    extracted = archive.extractfile(member)
                    assert extracted is not None
                    self.write(field, member.name, extracted)
                else:
                    raise UploadError(field, f"{member.name[:80]!r} is a link or device: only files are taken")


def scene_path(root: Path, name: str) -> Path:
    """The scene file named by the `scene` field, inside the upload."""
    path = root / relative_name("scene", name)
    if path.suffix.lower() not in SCENE_SUFFIXES:
        raise UploadError("scene", f"{name[:80]!r}: the scene must be a .json or .xml file")
    if not path.is_file():
        raise UploadError("scene", f"{name[:80]!r} is not in the upload")
    return path
