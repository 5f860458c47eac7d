"""The verdict of ``--fail-if`` gates as JUnit XML, for CI (GitLab, Jenkins, GitHub test
reporters). Pure: returns the text; the command writes it (atomically, :mod:`agvviz.recording.outputs`).

Shape (the fields those tools read)::

    <testsuites name="agvviz run" tests="2" failures="1" errors="0">
      <testsuite name="agvviz run qr_floor-lm" tests="2" failures="1" errors="0" skipped="0">
        <properties><property name="rrd" value="runs/qr_floor-lm.rrd"/></properties>
        <testcase classname="agvviz.run" name="suspects &gt; 0">
          <failure type="fail-if" message="'suspects &gt; 0' holds (suspects = 7)">…</failure>
        </testcase>
        <testcase classname="agvviz.run" name="frames &lt; 10"/>
        <system-out>suspect stretches …</system-out>
      </testsuite>
    </testsuites>

One ``<testcase>`` per ``--fail-if`` condition: passing when it does not hold, a ``<failure>``
when it holds, an ``<error>`` when it could not be evaluated (a metric without a value).
"""

from __future__ import annotations

import xml.etree.ElementTree as ET

from agvviz.evaluation.gates import Gate


def junit_xml(
    command: str,
    suite: str,
    gates: list[Gate],
    *,
    properties: dict[str, str] | None = None,
    details: str = "",
    time_s: float | None = None,
) -> str:
    """JUnit XML of ``gates``: one testsuite named ``suite`` (e.g. ``agvviz run <run name>``),
    one testcase per gate (classname ``agvviz.<command>``). ``properties`` (e.g. the .rrd
    paths) and ``details`` (``<system-out>``: e.g. the suspect stretches) describe the run;
    ``time_s`` the command's wall time (left out when None)."""
    failures = sum(g.holds is True for g in gates)
    errors = sum(g.holds is None for g in gates)
    counts = {"tests": str(len(gates)), "failures": str(failures), "errors": str(errors)}
    root = ET.Element("testsuites", {"name": f"agvviz {command}", **counts})
    suite_attrs = {"name": suite, **counts, "skipped": "0"}
    if time_s is not None:
        suite_attrs["time"] = f"{time_s:.3f}"
        root.set("time", f"{time_s:.3f}")
    element = ET.SubElement(root, "testsuite", suite_attrs)
    if properties:
        props = ET.SubElement(element, "properties")
        for name, value in properties.items():
            ET.SubElement(props, "property", {"name": str(name), "value": str(value)})
    for gate in gates:
        case = ET.SubElement(element, "testcase", {"classname": f"agvviz.{command}", "name": gate.condition})
        if gate.holds is True:
            failure = ET.SubElement(case, "failure", {"type": "fail-if", "message": gate.message})
            failure.text = _values_text(gate)
        elif gate.holds is None:
            error = ET.SubElement(case, "error", {"type": "fail-if", "message": gate.message})
            error.text = gate.error or ""
    if details:
        ET.SubElement(element, "system-out").text = details
    ET.indent(root)
    return '<?xml version="1.0" encoding="UTF-8"?>\n' + ET.tostring(root, encoding="unicode") + "\n"


def _values_text(gate: Gate) -> str:
    lines = [f"--fail-if {gate.condition}", "holds with:"]
    lines += [f"  {name} = {value}" for name, value in gate.values.items()]
    return "\n".join(lines)
