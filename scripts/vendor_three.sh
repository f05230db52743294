#!/usr/bin/env bash
# Re-vendors three.js into service/web/vendor/three/ from the npm registry (the web app loads nothing from a
# CDN): the minified ES module build, OrbitControls and the licence. Usage: scripts/vendor_three.sh [VERSION]
set -euo pipefail
version="${1:-0.170.0}"
target="$(cd "$(dirname "$0")/.." && pwd)/service/web/vendor/three"
work="$(mktemp -d)"
trap 'rm -rf "$work"' EXIT
(cd "$work" && npm pack --silent "three@${version}" >/dev/null && tar xzf "three-${version}.tgz")
mkdir -p "$target"
cp "$work/package/build/three.module.min.js" "$work/package/examples/jsm/controls/OrbitControls.js" \
   "$work/package/LICENSE" "$target/"
# The app loads modules by path, with no import map (an inline script, which its Content-Security-Policy
# refuses): OrbitControls imports three from its sibling file instead of the bare name.
sed -i "s#from 'three';#from './three.module.min.js';#" "$target/OrbitControls.js"
grep -q "from './three.module.min.js';" "$target/OrbitControls.js"
echo "three@${version}" > "$target/VERSION"
echo "vendored three@${version} into $target"
