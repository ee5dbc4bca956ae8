#!/usr/bin/env bash
# Chromium + its WebDriver for the viewer's browser test (tests/viewer/test_browser.py): use what is
# installed; install Debian's packages if root. Never downloads a browser any other way. Without
# them the browser test is skipped and says what to install.
set -euo pipefail
have() { command -v "$1" >/dev/null 2>&1; }
if { have chromium || have chromium-browser; } && have chromedriver; then exit 0; fi
if [ "$(id -u)" = "0" ] && have apt-get; then
  echo "chromium/chromedriver not found: installing Debian's chromium and chromium-driver (viewer browser test)"
  if apt-get update -qq && DEBIAN_FRONTEND=noninteractive apt-get install -y -qq chromium chromium-driver >/dev/null; then
    exit 0
  fi
  echo "note: could not install chromium chromium-driver; the viewer's browser test will be skipped" >&2
  exit 0
fi
echo "note: chromium and chromedriver not found; the viewer's browser test will be skipped" >&2
echo "      (Debian/Ubuntu: sudo apt-get install chromium chromium-driver)" >&2
exit 0
