"""Independent client: read so2lin's sample MCAP logs with the official Python `mcap`
package and validate every JSON message against the JSON Schema embedded in the file and,
with `--official DIR`, every Foxglove message against the official schema in DIR/<Name>.json
as well (from the npm package @foxglove/schemas, written by tests/foxglove_schemas.js).

Run by .ci/run inside a virtual environment (`pip install mcap jsonschema`):
    python tests/mcap_client.py [--official DIR] [--maintained] logs/*.mcap
"""
import os
import json
import sys
from collections import Counter

import jsonschema
from mcap.reader import make_reader

EXPECTED = {
    "/so2lin/edge": "so2lin.Edge",
    "/so2lin/step": "so2lin.Step",
    "/so2lin/estimate": "so2lin.Estimate",
    "/so2lin/log": "foxglove.Log",
    "/graph": "foxglove.SceneUpdate",
    "/poses": "foxglove.PosesInFrame",
    "/pose": "foxglove.PoseInFrame",
    "/so2lin/maintenance": "so2lin.Maintenance",
}


def stamp_ns(msg):
    """The Foxglove timestamp of a message, if it has one, in ns."""
    stamp = msg.get("timestamp")
    if stamp is None and msg.get("entities"):
        stamp = msg["entities"][0].get("timestamp")
    if stamp is None:
        return None
    return stamp["sec"] * 1_000_000_000 + stamp["nsec"]


def check(path, official=None, maintained=False):
    counts = Counter()
    validators = {}
    official_validators = {}
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        topics = {c.topic: summary.schemas[c.schema_id].name for c in summary.channels.values()}
        assert topics == EXPECTED, f"{path}: channels {topics}"
        meta = [m for m in reader.iter_metadata() if m.name == "so2lin"]
        assert len(meta) == 1, f"{path}: so2lin metadata record"
        for key in ("so2lin_version", "schema_version", "alpha", "dof", "basis", "source"):
            assert key in meta[0].metadata, f"{path}: metadata lacks {key}"
        for schema, channel, message in reader.iter_messages():
            assert schema.encoding == "jsonschema" and channel.message_encoding == "json"
            if schema.id not in validators:
                validators[schema.id] = jsonschema.Draft202012Validator(json.loads(schema.data))
            data = json.loads(message.data)
            validators[schema.id].validate(data)
            if official and schema.name.startswith("foxglove."):
                name = schema.name.removeprefix("foxglove.")
                if name not in official_validators:
                    with open(os.path.join(official, f"{name}.json")) as g:
                        official_validators[name] = jsonschema.Draft202012Validator(json.load(g))
                official_validators[name].validate(data)
            counts[channel.topic] += 1
            # One clock: log time, publish time and the Foxglove timestamp agree.
            assert message.log_time == message.publish_time, f"{path}: {channel.topic}"
            ns = stamp_ns(data)
            assert ns is None or ns == message.log_time, f"{path}: {channel.topic} {ns} vs {message.log_time}"
        stats = summary.statistics
    assert counts["/so2lin/edge"] == counts["/so2lin/step"] > 0, f"{path}: {counts}"
    assert counts["/so2lin/estimate"] >= 1, f"{path}: {counts}"
    assert counts["/graph"] == counts["/poses"] == counts["/so2lin/estimate"], f"{path}: {counts}"
    assert counts["/pose"] == counts["/so2lin/step"], f"{path}: the newest pose every step {counts}"
    steps = counts["/so2lin/step"]
    if maintained:
        assert counts["/so2lin/maintenance"] > 0, f"{path}: no renewal between steps {counts}"
    assert counts["/poses"] >= min(20, steps // 100 + 1), f"{path}: snapshots {counts}"
    span = (stats.message_end_time - stats.message_start_time) / 1e9
    assert span >= 0.05 * (steps - 1), f"{path}: {steps} steps play back in {span:.2f} s"
    assert sum(counts.values()) == stats.message_count, f"{path}: statistics {stats.message_count}"
    against = "its embedded schema" + (" and the official Foxglove one" if official else "")
    print(f"{path}: {dict(counts)} over {span:.1f} s — every message valid against {against}")


if __name__ == "__main__":
    usage = "usage: mcap_client.py [--official DIR] [--maintained] LOG.mcap ..."
    args = sys.argv[1:]
    official = None
    if args[:1] == ["--official"]:
        if len(args) < 2:
            sys.exit(usage)
        official, args = args[1], args[2:]
    # The logs were recorded with `stream --maintain`: they hold renewals between steps.
    maintained = args[:1] == ["--maintained"]
    if maintained:
        args = args[1:]
    if not args:
        sys.exit(usage)
    for p in args:
        check(p, official, maintained)
