"""What a run ran on: the commit a result records says whether the tree was that commit's."""

import subprocess

from clflow.environment import _commit


def test_the_commit_says_dirty_when_the_tree_differs_from_it(tmp_path):
    def git(*args):
        subprocess.run(["git", "-C", str(tmp_path), *args], check=True, capture_output=True)

    git("init", "-q")
    (tmp_path / "a.py").write_text("x = 1\n")
    git("add", "a.py")
    git("-c", "user.name=t", "-c", "user.email=t@t", "commit", "-qm", "one")
    git("-c", "user.name=t", "-c", "user.email=t@t", "tag", "v1")  # a tag does not replace the hash
    clean = _commit(tmp_path)
    assert clean is not None and len(clean) == 7 and int(clean, 16) >= 0
    (tmp_path / "a.py").write_text("x = 2\n")  # a copied tree whose git metadata lags looks the same
    assert _commit(tmp_path) == f"{clean}-dirty"
    assert _commit(tmp_path / "missing") is None
