#!/usr/bin/env node
// lint-openapi.js FILE: lints an OpenAPI 3.1 document with Redocly's lint
// engine (@redocly/openapi-core, what `redocly lint` runs) and the rules of
// redocly.yaml beside this file; prints every problem and exits 1 when
// there is any (warnings included), 0 when there is none.
'use strict';
const path = require('path');
const { lint, loadConfig, formatProblems, getTotals } = require('@redocly/openapi-core');

(async () => {
  const file = process.argv[2];
  if (!file) {
    console.error('usage: lint-openapi.js FILE');
    process.exit(2);
  }
  const config = await loadConfig({ configPath: path.join(__dirname, 'redocly.yaml') });
  const problems = await lint({ ref: file, config });
  const totals = getTotals(problems);
  formatProblems(problems, { format: 'stylish', totals, version: 'openapi-core' });
  console.log(`${file}: ${totals.errors} errors, ${totals.warnings} warnings`);
  process.exit(totals.errors + totals.warnings > 0 ? 1 : 0);
})().catch((e) => {
  console.error(e && e.stack ? e.stack : String(e));
  process.exit(2);
});
