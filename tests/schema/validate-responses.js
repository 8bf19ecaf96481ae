#!/usr/bin/env node
// validate-responses.js OPENAPI.yaml CASES.json: validates JSON response
// bodies against the schemas of an OpenAPI 3.1 document (JSON Schema
// 2020-12, ajv). CASES.json is an array of {"what", "pointer", "body"}:
// pointer is the JSON pointer of the schema inside the document. Prints
// each body that does not validate and exits 1 when there is one.
'use strict';
const fs = require('fs');
const yaml = require('js-yaml');
const Ajv2020 = require('ajv/dist/2020');

const doc = yaml.load(fs.readFileSync(process.argv[2], 'utf8'));
const cases = JSON.parse(fs.readFileSync(process.argv[3], 'utf8'));
doc.$id = 'urn:microray:openapi';
// strict off: the document's own keys (paths, components) are no schema
// keywords; formats are not checked (no ajv-formats here)
const ajv = new Ajv2020({ strict: false, validateFormats: false, allErrors: true });
ajv.addSchema(doc);
let bad = 0;
for (const c of cases) {
  const validate = ajv.getSchema('urn:microray:openapi#' + c.pointer);
  if (!validate) {
    console.log(`${c.what}: no schema at ${c.pointer}`);
    bad++;
    continue;
  }
  if (!validate(c.body)) {
    console.log(`${c.what}: the body does not match ${c.pointer}:`);
    for (const e of validate.errors.slice(0, 8))
      console.log(`  ${e.instancePath || '/'} ${e.message} ${JSON.stringify(e.params)}`);
    console.log(`  body: ${JSON.stringify(c.body).slice(0, 400)}`);
    bad++;
  }
}
console.log(`${cases.length} bodies checked, ${bad} not as documented`);
process.exit(bad ? 1 : 0);
