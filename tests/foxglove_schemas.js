// Write the official Foxglove JSON Schemas of the messages so2lin logs, from the npm package
// @foxglove/schemas (unpacked at PKG), as OUT/<Name>.json, for tests/mcap_client.py --official.
// Run by .ci/run: node tests/foxglove_schemas.js PKG OUT
const fs = require("fs");
const path = require("path");
const [pkg, out] = process.argv.slice(2);
if (!pkg || !out) {
  console.error("usage: node foxglove_schemas.js PKG OUT");
  process.exit(2);
}
const schemas = require(path.resolve(pkg, "dist/jsonschema/index.js"));
for (const name of ["Log", "SceneUpdate", "PoseInFrame", "PosesInFrame"]) {
  if (!schemas[name]) {
    console.error(`@foxglove/schemas has no ${name}`);
    process.exit(1);
  }
  fs.writeFileSync(path.join(out, `${name}.json`), JSON.stringify(schemas[name]));
}
console.log(`official Foxglove schemas written to ${out}`);
