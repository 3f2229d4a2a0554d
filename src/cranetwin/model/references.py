"""Cross-references of a machine description (names, the serial chain, actuators, channels),
checked on plain dicts so that a file with field errors still gets them reported."""

from __future__ import annotations

WORLD = "world"


def _names(items: object) -> list[str]:
    if not isinstance(items, list):
        return []
    return [str(x.get("name")) for x in items if isinstance(x, dict)]


def reference_problems(data: dict[str, object]) -> list[str]:
    """Cross-references in a (raw or dumped) machine description, as ``"path: message"`` lines.

    Works on plain dicts so that a file with field errors still gets its references checked.
    """
    problems: list[str] = []
    bodies = _names(data.get("bodies"))
    joints_raw = data.get("joints")
    joints = [j for j in joints_raw if isinstance(j, dict)] if isinstance(joints_raw, list) else []
    joint_names = [str(j.get("name")) for j in joints]
    if len(set(bodies)) != len(bodies):
        problems.append("bodies: names must be unique")
    if len(set(joint_names)) != len(joint_names):
        problems.append("joints: names must be unique")
    expected_parent = WORLD
    for i, j in enumerate(joints):
        if j.get("child") not in bodies:
            problems.append(f"joints.{i}.child: unknown body {j.get('child')!r}")
        if j.get("parent") != expected_parent:
            problems.append(
                f"joints.{i}.parent: {j.get('parent')!r} breaks the serial chain "
                f"(expected {expected_parent!r})"
            )
        expected_parent = str(j.get("child"))
    actuated: set[str] = set()
    actuator_names: set[str] = set()
    for kind in ("cylinders", "torque_drives"):
        acts = data.get(kind)
        for i, a in enumerate(acts if isinstance(acts, list) else []):
            if not isinstance(a, dict):
                continue
            actuator_names.add(str(a.get("name")))
            joint = a.get("joint")
            if joint not in joint_names:
                problems.append(f"{kind}.{i}.joint: unknown joint {joint!r}")
            elif joint in actuated:
                problems.append(f"{kind}.{i}.joint: joint {joint!r} already has an actuator")
            actuated.add(str(joint))
    for i, (name, j) in enumerate(zip(joint_names, joints, strict=True)):
        fixed = j.get("fixed_value") is not None
        if name not in actuated and not fixed:
            problems.append(f"joints.{i}: joint {name!r} has no actuator; a passive joint "
                            "declares the value it is held at (fixed_value)")
        elif name in actuated and fixed:
            problems.append(f"joints.{i}.fixed_value: joint {name!r} has an actuator; only a "
                            "passive joint (no actuator) is held at a fixed value")
    channels_raw = data.get("channels")
    channels = [c for c in channels_raw if isinstance(c, dict)] if isinstance(
        channels_raw, list) else []
    channel_names = [str(c.get("name")) for c in channels]
    if len(set(channel_names)) != len(channel_names):
        problems.append("channels: names must be unique")
    for i, c in enumerate(channels):
        source = c.get("source")
        if c.get("quantity") == "angle":
            if source not in joint_names:
                problems.append(f"channels.{i}.source: unknown joint {source!r}")
        elif c.get("quantity") != "load" and source not in actuator_names:
            problems.append(f"channels.{i}.source: unknown actuator {source!r}")
    load_point = data.get("load_point")
    if isinstance(load_point, dict) and load_point.get("body") not in bodies:
        problems.append(f"load_point.body: unknown body {load_point.get('body')!r}")
    if data.get("cylinders") and data.get("hydraulics") is None:
        problems.append("hydraulics: required when the machine has cylinders")
    return problems
