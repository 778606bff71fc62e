// Validate one binary glTF file with the Khronos glTF validator and print its JSON report
// (issues.numErrors, numWarnings, numInfos, numHints and the messages) on stdout.
// Usage: node validate.mjs model.glb   (exit 0 when the report was made, 2 on bad usage)
import { readFile } from "node:fs/promises";
import validator from "gltf-validator";

const path = process.argv[2];
if (!path) {
  console.error("usage: node validate.mjs <file.glb>");
  process.exit(2);
}
const bytes = new Uint8Array(await readFile(path));
const report = await validator.validateBytes(bytes, { uri: path, maxIssues: 0 });
console.log(JSON.stringify(report, null, 2));
