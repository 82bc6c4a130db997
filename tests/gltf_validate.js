// node gltf_validate.js VALIDATOR_DIR FILE.glb: the Khronos glTF validator's verdict on a file, as
// JSON on stdout ({errors, warnings, infos, messages: [[severity, code, message, pointer], ...]}).
const [validatorDir, path] = process.argv.slice(2);
const validator = require(validatorDir);
const bytes = new Uint8Array(require("fs").readFileSync(path));
validator.validateBytes(bytes).then((report) => {
  const issues = report.issues;
  console.log(JSON.stringify({
    errors: issues.numErrors, warnings: issues.numWarnings, infos: issues.numInfos,
    messages: issues.messages.map((m) => [m.severity, m.code, m.message, m.pointer]),
  }));
}).catch((error) => { console.error(String(error)); process.exit(1); });
