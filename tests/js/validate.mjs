// The Khronos glTF validator on each file named: one JSON line per file, its issue counts and first messages.
import { createRequire } from 'node:module';
import { readFileSync } from 'node:fs';

const validator = createRequire(import.meta.url)('gltf-validator');
for (const path of process.argv.slice(2)) {
  const report = await validator.validateBytes(new Uint8Array(readFileSync(path)), { maxIssues: 50 });
  const { numErrors, numWarnings, numInfos, messages } = report.issues;
  console.log(JSON.stringify({ path, numErrors, numWarnings, numInfos, messages: messages.slice(0, 10) }));
}
