"""The logging tests: the MCAP logger alone (test_mcap_logger.py) and the node's logs
(test_mcap_node.py). test_mcap_node.py drives the node with the client of the node tests, so
test/node/ (node_fixtures.py) is put on sys.path here, whichever folder pytest collects first.
"""
import sys
from pathlib import Path

NODE_TESTS = str(Path(__file__).resolve().parents[1] / "node")


def pytest_configure(config):
    if NODE_TESTS not in sys.path:
        sys.path.append(NODE_TESTS)
