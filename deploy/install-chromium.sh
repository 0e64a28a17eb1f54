#!/usr/bin/env bash
# Debian's chromium, for the HTML report's browser test (tests/helpers/chromium.py,
# driven by playwright, which never downloads a browser of its own). `make test`
# runs this before pytest: nothing to do (and no time spent) when chromium is
# there; as root, installs it quietly with apt-get (and a font for the page's
# text); as anyone else, says how, and the browser test skips with the same words.
# Exits non-zero only if an install as root failed: CI (root) must run the test.
# BATON_APT_DEADLINE (600): seconds for each apt-get step.
set -euo pipefail

if command -v chromium >/dev/null 2>&1; then
    exit 0
fi
if [ "$(id -u)" != 0 ]; then
    echo "install-chromium: no chromium, and only root installs it: sudo apt-get install chromium" \
        "(the HTML report's browser test is skipped)" >&2
    exit 0
fi
if ! command -v apt-get >/dev/null 2>&1; then
    echo "install-chromium: no chromium and no apt-get to install it (a Debian-based machine" \
        "is expected)" >&2
    exit 1
fi
deadline=${BATON_APT_DEADLINE:-600}
echo "install-chromium: installing Debian's chromium (apt-get)" >&2
export DEBIAN_FRONTEND=noninteractive
timeout "$deadline" apt-get update -qq
timeout "$deadline" apt-get install -y -qq --no-install-recommends chromium fonts-dejavu-core \
    >/dev/null
command -v chromium >/dev/null
