"""The explorer page in a real headless browser (Debian's chromium and
chromium-driver, driven by selenium): it loads from file:// with no console
error, its videos play, and clicking a slot shows that slot's
counterfactual rollout. Skipped, with the reason, where no browser is
installed (`.ci/run` installs one)."""

import os
import shutil
import time

import pytest

from explore_helpers import write_micro_page

try:
  from selenium import webdriver
  from selenium.webdriver.chrome.service import Service
  from selenium.webdriver.common.by import By
except ImportError:
  webdriver = None

CHROMIUM = shutil.which('chromium') or '/usr/bin/chromium'
CHROMEDRIVER = '/usr/bin/chromedriver'


def _driver():
  if webdriver is None:
    pytest.skip('selenium is not installed (pip install -e ".[test]")')
  if not (os.path.exists(CHROMIUM) and os.path.exists(CHROMEDRIVER)):
    pytest.skip('no headless browser: apt-get install -y chromium '
                'chromium-driver')
  options = webdriver.ChromeOptions()
  for argument in ('--headless=new', '--no-sandbox', '--disable-gpu',
                   '--disable-dev-shm-usage', '--window-size=1400,1600'):
    options.add_argument(argument)
  options.binary_location = CHROMIUM
  options.set_capability('goog:loggingPrefs', {'browser': 'ALL'})
  # The driver's path is given: Selenium Manager never downloads one.
  return webdriver.Chrome(service=Service(CHROMEDRIVER), options=options)


@pytest.fixture(scope='module')
def page(tmp_path_factory):
  driver = _driver()
  root = tmp_path_factory.mktemp('explore')
  path, data = write_micro_page(root, root / 'data')
  driver.get('file://' + path)
  yield driver, data
  driver.quit()


def _wait_for(condition, timeout=10.0):
  deadline = time.monotonic() + timeout
  while time.monotonic() < deadline:
    value = condition()
    if value:
      return value
    time.sleep(0.1)
  return condition()


def test_page_loads_without_console_errors(page):
  driver, data = page
  assert _wait_for(lambda: driver.find_element(By.TAG_NAME, 'body')
                   .get_attribute('data-frame') is not None)
  errors = [entry for entry in driver.get_log('browser')
            if entry['level'] in ('SEVERE', 'ERROR')]
  assert errors == []
  assert driver.title == data['title']
  labels = [e.text for e in driver.find_elements(
      By.CSS_SELECTOR, '#rollouts figcaption')]
  assert labels == ['truth', 'SAVi masks', 'SlotFormer', 'SlotFormer masks',
                    'Slot-LSTM', 'copy-last']
  assert 'test' in driver.find_element(By.ID, 'identity').text


def test_videos_play(page):
  driver, _ = page
  body = driver.find_element(By.TAG_NAME, 'body')
  first = body.get_attribute('data-frame')
  assert _wait_for(lambda: body.get_attribute('data-frame') != first)
  truth = driver.find_element(By.CSS_SELECTOR, '#rollouts canvas')
  before = truth.screenshot_as_png
  assert _wait_for(lambda: truth.screenshot_as_png != before)


def test_clicking_a_slot_shows_its_counterfactual_rollout(page):
  driver, data = page
  play = driver.find_element(By.ID, 'play')
  if play.text == 'pause':
    play.click()  # a still frame, so the panel's pixels compare
  # A predicted frame, where the interventions differ.
  driver.execute_script('window.explorer.state.frame = arguments[0];'
                        'window.explorer.selectSlot(0);',
                        data['burn_in'] + data['rollout'] - 1)
  panel = driver.find_element(By.ID, 'counterfactual')
  assert panel.get_attribute('data-slot') == '0'
  intervened = lambda: driver.find_element(
      By.CSS_SELECTOR, '#cf-tiles canvas[data-source^="remove/"]')
  assert intervened().get_attribute('data-source') == 'remove/0'
  before = intervened().screenshot_as_png
  driver.find_element(By.ID, 'slot-2').click()
  assert panel.get_attribute('data-slot') == '2'
  assert intervened().get_attribute('data-source') == 'remove/2'
  assert 'slot 2 removed' in panel.text
  assert 'selected' in driver.find_element(By.ID, 'slot-2').get_attribute(
      'class')
  assert intervened().screenshot_as_png != before
  driver.find_element(By.ID, 'kind-freeze').click()
  assert panel.get_attribute('data-kind') == 'freeze'
  assert driver.find_element(
      By.CSS_SELECTOR, '#cf-tiles canvas[data-source="freeze/2"]')
  assert 'slot 2 frozen' in panel.text
  errors = [entry for entry in driver.get_log('browser')
            if entry['level'] in ('SEVERE', 'ERROR')]
  assert errors == []


# Method and metric names as eval/metrics.json of a shared run folder may
# hold them: markup that runs script if it is ever parsed as HTML.
_HOSTILE = '<img src=x onerror="document.body.dataset.owned=1">'


@pytest.fixture(scope='module')
def hostile_page(tmp_path_factory):
  driver = _driver()
  root = tmp_path_factory.mktemp('hostile')
  path, data = write_micro_page(
      root, root / 'data', curves={
          _HOSTILE + 'metric': {_HOSTILE + 'method': [1.0, 2.0],
                                'constructor': [2.0, 1.0]},
          '</script><script>document.body.dataset.owned=2</script>': {
              'SlotFormer': [1.0, 1.5]}})
  driver.get('file://' + path)
  yield driver, data
  driver.quit()


def test_names_from_the_metrics_file_are_shown_as_text(hostile_page):
  """The charts' titles and legend are text nodes: a name with markup is
  shown as it is and runs nothing (before, `charts()` put the names into
  innerHTML and the onerror handler ran). The page's JSON closes no
  element either."""
  driver, _ = hostile_page
  body = driver.find_element(By.TAG_NAME, 'body')
  assert _wait_for(lambda: body.get_attribute('data-frame') is not None)
  time.sleep(0.5)  # an image error handler would have run by now
  assert body.get_attribute('data-owned') is None
  legend = driver.find_element(By.CSS_SELECTOR, '#run-charts .legend').text
  assert _HOSTILE + 'method' in legend and 'constructor' in legend, legend
  titles = [e.text for e in driver.find_elements(
      By.CSS_SELECTOR, '#run-charts svg.chart > text:first-of-type')]
  assert _HOSTILE + 'metric' in titles, titles
  assert not driver.find_elements(By.CSS_SELECTOR, '#run-charts img')
  errors = [entry for entry in driver.get_log('browser')
            if entry['level'] in ('SEVERE', 'ERROR')]
  assert errors == []
