import re

import sb3_hieros


def test_version_is_semver():
    assert re.fullmatch(r"\d+\.\d+\.\d+", sb3_hieros.__version__)
