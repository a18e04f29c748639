"""A URDF text -> yourdfpy's model, keeping what of a malformed description can be kept.

A malformed description costs what is malformed, not the robot: XML cut short (a truncated
string) keeps the elements complete before the error; an element yourdfpy refuses (a joint
without a parent, ``xyz="1 two 3"``) is left out, each tried on its own. What was left out is
returned as problems, which the converter (description.py) names in its one
PartialConvertError; the joints' own faults are kinematics.py's. (urdfdom refuses such a model
whole, so RViz draws nothing; a viewer should show what it can and say what it left out.)
"""

from __future__ import annotations

import io
import xml.etree.ElementTree as ET
from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np

from host_bridge.errors import ConvertError

if TYPE_CHECKING:
    # Imported where a model is built: yourdfpy (with trimesh and scipy) takes about a second to
    # import, which every --bag run without a robot description paid.
    import yourdfpy

# Problems of one kind listed in a warning before "and N more": a 10k-link model with every
# joint wrong must still give a warning one can read.
_LISTED_PROBLEMS = 10
# What yourdfpy raises on an element it cannot read (a missing attribute or child, a number
# that is not one): whatever failed while reading it.
_URDF_ERRORS = (AttributeError, KeyError, ValueError, TypeError, IndexError)


def parse(xml: str, source: str) -> tuple[yourdfpy.URDF, list[str]]:
    """The URDF, and what of it was left out: the elements after the point where the XML stops
    being well-formed, and the elements yourdfpy cannot read (each tried on its own)."""
    data = xml.encode("utf-8")
    root, problems = _well_formed_part(data, source)
    if root.get("name") is None:
        problems.append("the <robot> element has no name attribute")
        root.set("name", "")
    import yourdfpy

    def load(document: bytes) -> yourdfpy.URDF:
        # A non-finite rpy makes trimesh's sin/cos warn on stderr; kinematics.py names it.
        with np.errstate(invalid="ignore"):
            return yourdfpy.URDF.load(
                io.BytesIO(document), build_scene_graph=False, load_meshes=False
            )

    try:
        return load(ET.tostring(root) if problems else data), problems
    except _URDF_ERRORS as err:
        # yourdfpy reports a missing required element as whatever failed while reading it.
        refusal = f"{type(err).__name__}: {err}"
    kept = ET.Element(root.tag, root.attrib)
    refused = []
    for element in root:
        alone = ET.Element(root.tag, root.attrib)
        alone.append(element)
        try:
            load(ET.tostring(alone))
        except _URDF_ERRORS as err:
            refused.append(f"{_element_name(element)} ({type(err).__name__}: {err})")
            continue
        kept.append(element)
    if kept.find("link") is None:
        msg = f"{source}: the robot description is not a valid URDF ({refusal})"
        raise ConvertError(msg)
    problems.append(f"not valid URDF, not drawn: {listed(refused)}")
    try:
        return load(ET.tostring(kept)), problems
    except _URDF_ERRORS as err:
        msg = f"{source}: the robot description is not a valid URDF ({refusal})"
        raise ConvertError(msg) from err


def _well_formed_part(data: bytes, source: str) -> tuple[ET.Element, list[str]]:
    """The document's root element; for XML that is not well-formed (a description cut short,
    a stray byte) the root with the children that were complete before the error, and the
    problem. The stdlib parser, not yourdfpy's lxml one: that falls back to a "recover" mode
    that silently drops or mends what is broken."""
    parser: ET.XMLPullParser[ET.Element] = ET.XMLPullParser(events=("start", "end"))
    parser.feed(data)
    error: ET.ParseError | None = None
    try:
        parser.close()
    except ET.ParseError as err:
        error = err
    root: ET.Element | None = None
    complete: list[ET.Element] = []
    depth = 0
    try:
        for pair in parser.read_events():
            event, element = pair[0], pair[-1]
            if not isinstance(element, ET.Element):
                continue  # only namespace events carry something else; none were asked for
            if event == "start":
                root = element if root is None else root
                depth += 1
            else:
                depth -= 1
                if depth == 1:
                    complete.append(element)
    except ET.ParseError as err:
        error = err  # the first error, from feed(); close() then reports a later one
    if root is not None and root.tag != "robot":
        msg = f"{source}: the robot description's root element is <{root.tag}>, not <robot>"
        raise ConvertError(msg)
    if error is None and root is not None:
        return root, []
    if root is None or not complete:
        msg = f"{source}: the robot description is not well-formed XML ({error})"
        raise ConvertError(msg)
    salvaged = ET.Element(root.tag, root.attrib)
    salvaged.extend(complete)
    problem = (
        f"the description is not well-formed XML ({error}): only the {len(complete)} elements "
        "complete before that point are drawn"
    )
    return salvaged, [problem]


def _element_name(element: ET.Element) -> str:
    name = element.get("name")
    return f"<{element.tag}>" if name is None else f"<{element.tag} name={name!r}>"


def listed(problems: Sequence[str]) -> str:
    shown = ", ".join(problems[:_LISTED_PROBLEMS])
    more = len(problems) - _LISTED_PROBLEMS
    return shown if more <= 0 else f"{shown} and {more} more"
