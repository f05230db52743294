"""bench_features.py's command line: the retrieval vocabulary's training caps."""

from __future__ import annotations

import argparse

import pytest


@pytest.fixture
def bench(benchmark_module):
    return benchmark_module("bench_features")


def test_vocabulary_caps_are_whole_numbers_with_zero_for_every_descriptor(bench):
    assert bench.descriptor_caps("20000,0,10000") == [20000, 0, 10000]


@pytest.mark.parametrize("text", ["", "20000,-1", "20000,lots", "1.5"])
def test_a_cap_that_is_no_whole_number_or_is_negative_is_refused_naming_the_option(bench, text):
    with pytest.raises(argparse.ArgumentTypeError, match="--vocabulary-descriptors") as refused:
        bench.descriptor_caps(text)
    assert repr(text) in str(refused.value)
