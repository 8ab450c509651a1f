"""pyproject.toml names every folder of modules it installs (setuptools warns "Package would be
ignored" for a folder of .py files that is not listed, and does not install it)."""
import os
import tomllib

REPO = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))


def test_every_folder_of_modules_is_a_listed_package():
    with open(os.path.join(REPO, "pyproject.toml"), "rb") as f:
        tool = tomllib.load(f)["tool"]["setuptools"]
    packages, roots = set(tool["packages"]), tool["package-dir"]
    for package, root in roots.items():
        for folder, dirs, files in os.walk(os.path.join(REPO, root)):
            dirs[:] = [d for d in dirs if d != "__pycache__"]
            if any(name.endswith(".py") for name in files):
                relative = os.path.relpath(folder, os.path.join(REPO, root))
                name = package if relative == "." else \
                    package + "." + relative.replace(os.sep, ".")
                assert name in packages, f"{folder} holds modules but {name} is not listed"
