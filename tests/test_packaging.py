"""pyproject.toml installs the package as a plain src layout: src/muscle_mss/ holds links to the
root's core/, filters/, app/ and plugin/ (setuptools then needs no import hook for an editable
install, and prints no warning about folders that could shadow the package), and it names every
folder of modules it installs (setuptools warns "Package would be ignored" for a folder of .py
files that is not listed, and does not install it)."""
import os
import tomllib

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PACKAGE_FOLDERS = ("core", "filters", "app", "plugin")


def _setuptools() -> dict:
    with open(os.path.join(REPO, "pyproject.toml"), "rb") as f:
        return tomllib.load(f)["tool"]["setuptools"]


def test_the_package_is_a_src_layout_of_links_to_the_root_folders():
    assert _setuptools()["package-dir"] == {"": "src"}
    package = os.path.join(REPO, "src", "muscle_mss")
    assert sorted(os.listdir(package)) == sorted(PACKAGE_FOLDERS)
    for name in PACKAGE_FOLDERS:
        link = os.path.join(package, name)
        assert os.path.islink(link), f"{link} is not a link: the sources live in {name}/"
        assert os.path.realpath(link) == os.path.realpath(os.path.join(REPO, name))


def test_every_folder_of_modules_is_a_listed_package():
    packages = set(_setuptools()["packages"])
    root = os.path.join(REPO, "src")
    for folder, dirs, files in os.walk(root, followlinks=True):
        dirs[:] = [d for d in dirs if d != "__pycache__"]
        name = os.path.relpath(folder, root).replace(os.sep, ".")
        if name == "muscle_mss" or any(n.endswith(".py") for n in files):
            assert name in packages, f"{folder} holds modules but {name} is not listed"
