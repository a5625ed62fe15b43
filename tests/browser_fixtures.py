"""One plain headless Chromium per test worker, handed to each test clean: starting Chromium
costs seconds on a busy CI, and most browser tests need nothing of their own in it.

    from tests.browser_fixtures import browser_fixture  # noqa: F401 (the `browser` fixture)

(the worker's one Chromium is conftest.py's ``shared_chromium``: a session fixture defined
there, not in an imported module, so that every module gets the same one).
After each test the page is left (its sessions and timers end), the origin's storage and the
cookies are cleared and other tabs closed; a Chromium that cannot be reset is replaced. Tests
that need a fake camera file or WebRTC flags still start their own (make_chromium's
``camera_file``, make_webrtc_chromium)."""

from __future__ import annotations

import pytest

from tests.test_client_units import make_chromium


class SharedChromium:
    def __init__(self) -> None:
        self.driver = None

    def get(self):
        if self.driver is None:
            self.driver = make_chromium()
        return self.driver

    def reset(self) -> None:
        from selenium.common.exceptions import WebDriverException

        driver = self.driver
        if driver is None:
            return
        try:
            for handle in driver.window_handles[1:]:
                driver.switch_to.window(handle)
                driver.close()
            driver.switch_to.window(driver.window_handles[0])
            # the storage of the origin the test ended on (a page of the test's server)
            driver.execute_script("try { localStorage.clear(); sessionStorage.clear(); } "
                                  "catch (e) {}")
            driver.delete_all_cookies()
            driver.get("about:blank")
        except WebDriverException:  # an alert left open, a crashed tab: start afresh
            self.close()

    def close(self) -> None:
        if self.driver is not None:
            try:
                self.driver.quit()
            finally:
                self.driver = None


@pytest.fixture(name="browser")
def browser_fixture(shared_chromium):
    """The worker's plain Chromium (1280 x 900, the fake camera's test pattern), clean."""
    driver = shared_chromium.get()
    try:
        yield driver
    finally:
        shared_chromium.reset()
