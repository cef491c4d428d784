"""The suite's compile level (tests/compile_level.py) and the way back to a
user's: what each sets, and that jax reads the setting of op locations."""

import os

import jax

import compile_level


def test_the_suite_level_and_the_users_level():
  environ = {'XLA_FLAGS': '--xla_force_host_platform_device_count=4'}
  compile_level.apply(environ)
  assert environ[compile_level.SWITCH_ENV] == '1'
  assert environ[compile_level.LOCATIONS_ENV] == '0'
  assert environ['XLA_FLAGS'].split() == [
      '--xla_force_host_platform_device_count=4',
      *compile_level.SUITE_XLA_FLAGS]
  users = compile_level.as_users_compile(environ)
  assert users[compile_level.SWITCH_ENV] == '0'
  assert users[compile_level.LOCATIONS_ENV] == '1'
  assert users['XLA_FLAGS'] == '--xla_force_host_platform_device_count=4'


def test_the_users_level_is_left_alone():
  environ = {compile_level.SWITCH_ENV: '0'}
  compile_level.apply(environ)
  assert environ == {compile_level.SWITCH_ENV: '0'}


def test_jax_reads_the_locations_setting():
  locations = os.environ.get(compile_level.LOCATIONS_ENV, '1')
  assert jax.config.jax_include_full_tracebacks_in_locations == (
      locations == '1')
