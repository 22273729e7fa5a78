"""Read and write STEP (ISO 10303-21) files as solids in millimetres.

The part frame is the STEP model's own frame; OCCT scales lengths from the
file's declared unit (inch, metre, ...) to millimetres while reading.

References
----------
.. [1] ISO 10303-21:2016, Industrial automation systems and integration --
       Product data representation and exchange -- Part 21: Implementation
       methods: Clear text encoding of the exchange structure.
"""

import contextlib
import os
from datetime import datetime
from pathlib import Path

from partinspect.errors import InputError

__all__ = ["load_step", "save_step", "check_step_file", "quiet_occt"]

# ISO 10303-21 section 5: the exchange structure starts with this keyword and
# ends with its END- twin. A file without the end keyword was cut short.
_MAGIC = b"ISO-10303-21;"
_END = b"END-ISO-10303-21;"
_HEAD_BYTES = 4096
_TAIL_BYTES = 4096

# OCCT holds a whole STEP model in memory, several times the file's size;
# a machined part is a few MB, even a detailed assembly rarely 100 MB. Past
# this a file is refused before it is read, not after minutes of swapping.
MAX_STEP_BYTES = 500 * 2**20

# The STEP header's time stamp, fixed so that saving the same shape twice
# gives the same bytes (a constant, not a record of when anything was made).
_TIMESTAMP = datetime(2000, 1, 1).isoformat()


def load_step(path):
    """Load the solid(s) of a STEP file, in millimetres.

    Parameters
    ----------
    path : str or os.PathLike
        A STEP Part 21 file (AP203, AP214 or AP242; ``.step``/``.stp``).

    Returns
    -------
    shape : cadquery.Solid or cadquery.Compound
        The part in its STEP frame, lengths in mm whatever unit the file
        declares. A file holding exactly one solid gives that
        ``cadquery.Solid``; several solids give a ``cadquery.Compound`` of
        them. Shells, faces and wires that are not part of a solid are
        ignored.

    Raises
    ------
    partinspect.errors.InputError
        If the file is missing, empty, not a Part 21 file (checked from its
        header before OCCT sees it), cut short (no ``END-ISO-10303-21;``
        keyword at its end), unreadable by OCCT, or holds no solid. The
        message names the path.

    Notes
    -----
    The checks on the file's first and last bytes are not pedantry: OCCT
    7.9's reader leaves a null model behind after a syntax error, and several
    calls on such a reader crash the interpreter instead of raising, so a bad
    file must be caught before it reaches OCCT, and the reader is never
    queried after a failed read. OCCT's own console messages are silenced
    during the read so the command line shows one clear line.

    The target unit is set on the reader itself (``SetSystemLengthUnit``),
    not through OCCT's process-wide ``xstep.cascade.unit`` setting, which
    other code (cadquery's importer, for one) may have changed.
    """
    path = Path(path)
    _check_file(path)

    from OCP.IFSelect import IFSelect_RetDone
    from OCP.STEPControl import STEPControl_Reader

    reader = STEPControl_Reader()
    with _quiet_occt():
        try:
            status = reader.ReadFile(os.fspath(path))
        except Exception as exc:  # OCCT raises Standard_Failure subclasses
            raise InputError(path, f"OCCT could not parse the STEP file ({_occ_message(exc)})") from None
        if status != IFSelect_RetDone:
            raise InputError(path, "OCCT could not parse the STEP file (syntax error or unsupported content)")
        try:
            reader.SetSystemLengthUnit(1.0)  # OCCT's length unit is given in mm
            if reader.NbRootsForTransfer() == 0:
                raise InputError(path, "STEP file holds no shape to transfer (no product geometry)")
            reader.TransferRoots()
            shapes = [reader.Shape(i) for i in range(1, reader.NbShapes() + 1)]
        except InputError:
            raise
        except Exception as exc:
            raise InputError(path, f"OCCT could not convert the STEP data to shapes ({_occ_message(exc)})") from None
    return _solids_of(path, shapes)


def save_step(shape, path, name="part"):
    """Write a shape to a STEP AP214 file in millimetres, reproducibly.

    Parameters
    ----------
    shape : cadquery.Shape or OCP.TopoDS.TopoDS_Shape
        The part, lengths in mm, in its part frame.
    path : str or os.PathLike
        The file to write.
    name : str
        Written into the header's FILE_NAME record.

    Notes
    -----
    OCCT stamps the current time into the header and names the product
    after a per-process counter of writes; a fixed time stamp and ``name``
    are written instead, so the same shape always gives the same bytes.
    """
    from OCP.APIHeaderSection import APIHeaderSection_MakeHeader
    from OCP.IFSelect import IFSelect_RetDone
    from OCP.Interface import Interface_Static
    from OCP.STEPControl import STEPControl_AsIs, STEPControl_Writer
    from OCP.TCollection import TCollection_HAsciiString

    wrapped = getattr(shape, "wrapped", shape)
    writer = STEPControl_Writer()
    # These are process-wide settings; set every one the output depends on.
    Interface_Static.SetCVal_s("xstep.cascade.unit", "MM")
    Interface_Static.SetCVal_s("write.step.unit", "MM")
    Interface_Static.SetCVal_s("write.step.schema", "AP214IS")
    Interface_Static.SetIVal_s("write.surfacecurve.mode", 1)
    Interface_Static.SetIVal_s("write.precision.mode", 0)
    with _quiet_occt():
        writer.Transfer(wrapped, STEPControl_AsIs)
        _name_products(writer.Model(), str(name))
        header = APIHeaderSection_MakeHeader(writer.Model())
        header.SetName(TCollection_HAsciiString(str(name)))
        header.SetTimeStamp(TCollection_HAsciiString(_TIMESTAMP))
        status = writer.Write(os.fspath(path))
    if status != IFSelect_RetDone:
        raise OSError(f"{path}: OCCT could not write the STEP file ({status})")


def _name_products(model, name):
    """Give every PRODUCT of a STEP model being written the same fixed name."""
    from OCP.StepBasic import StepBasic_Product
    from OCP.TCollection import TCollection_HAsciiString

    for i in range(1, model.NbEntities() + 1):
        entity = model.Value(i)
        if isinstance(entity, StepBasic_Product):
            entity.SetId(TCollection_HAsciiString(name))
            entity.SetName(TCollection_HAsciiString(name))


def _check_file(path):
    """Reject what OCCT must never see: see `load_step` Notes."""
    if not path.exists():
        raise InputError(path, "no such file")
    if path.is_dir():
        raise InputError(path, "is a directory, not a STEP file")
    try:
        size = path.stat().st_size
        if size > MAX_STEP_BYTES:
            raise InputError(
                path, f"STEP file is too large ({size / 2**20:.0f} MB; the limit is {MAX_STEP_BYTES // 2**20} MB)"
            )
        with open(path, "rb") as f:
            head = f.read(_HEAD_BYTES)
            f.seek(max(0, size - _TAIL_BYTES))
            tail = f.read()
    except OSError as exc:
        raise InputError(path, f"cannot be read ({exc.strerror or exc})") from None
    if size == 0:
        raise InputError(path, "file is empty")
    start = head.lstrip(b"\xef\xbb\xbf \t\r\n")  # UTF-8 byte order mark, blank lines
    if not start.startswith(_MAGIC):
        raise InputError(path, f"not a STEP file: {_describe_start(start)}")
    # A complete file ends with the end keyword, at most followed by blanks
    # or comments: look for it in the last few kB.
    if _END not in tail:
        raise InputError(path, "STEP file is truncated (no END-ISO-10303-21; at its end)")


def _describe_start(start):
    """Say in a few words what a file that is not Part 21 looks like."""
    if start.startswith(b"\x1f\x8b") or start.startswith(b"PK\x03\x04"):
        return "it is compressed (gzip/zip, e.g. .stpZ); unpack it first"
    if start.lstrip().startswith(b"<"):
        return "it looks like XML (STEP-XML, ISO 10303-28, is not supported)"
    if start.startswith(b"ISO-10303-"):
        return "unsupported exchange structure " + start[:16].decode("ascii", "replace")
    return "it does not start with ISO-10303-21;"


def _solids_of(path, shapes):
    """One cadquery Solid, or a Compound of several; InputError if none."""
    import cadquery as cq
    from OCP.TopAbs import TopAbs_FACE, TopAbs_SHELL, TopAbs_SOLID
    from OCP.TopoDS import TopoDS

    solids = []
    n_shells = n_faces = 0
    for shape in shapes:
        if shape.IsNull():
            continue
        solids += [cq.Solid(TopoDS.Solid_s(s)) for s in _subshapes(shape, TopAbs_SOLID)]
        n_shells += len(_subshapes(shape, TopAbs_SHELL))
        n_faces += len(_subshapes(shape, TopAbs_FACE))
    if not solids:
        if n_faces:
            raise InputError(
                path, f"STEP file holds no solid, only surfaces ({n_shells} shells, {n_faces} faces); a solid model is needed"
            )
        raise InputError(path, "STEP file holds no solid")
    if len(solids) == 1:
        return solids[0]
    return cq.Compound.makeCompound(solids)


def _subshapes(shape, kind):
    from OCP.TopExp import TopExp_Explorer

    out = []
    explorer = TopExp_Explorer(shape, kind)
    while explorer.More():
        out.append(explorer.Current())
        explorer.Next()
    return out


def _occ_message(exc):
    text = " ".join(str(exc).split())
    return text or type(exc).__name__


@contextlib.contextmanager
def _quiet_occt():
    """Detach OCCT's console printers for the duration of the block.

    OCCT reports syntax errors of a STEP file on stdout in colour; the CLI
    must show one line of its own instead. The printers are put back
    afterwards, since the messenger is process-wide.
    """
    from OCP.Message import Message

    messenger = Message.DefaultMessenger_s()
    printers = list(messenger.Printers())
    for printer in printers:
        messenger.RemovePrinter(printer)
    try:
        yield
    finally:
        for printer in printers:
            messenger.AddPrinter(printer)


# Public names for the other STEP reader (partinspect.cad.pmi): the same
# checks before OCCT sees a file, the same silence while it reads.
check_step_file = _check_file
quiet_occt = _quiet_occt
