"""Where a scene's caches go: next to the data, or this user's cache folder when the data cannot be written."""

from pathlib import Path

from frugalnerf_ns import cache


def test_a_writable_scene_caches_next_to_its_data_and_a_json_names_its_folder(tmp_path):
    said = []
    (tmp_path / "scene").mkdir()
    (tmp_path / "scene" / "transforms.json").write_text("{}")
    assert cache.scene_cache_dir(tmp_path / "scene", said.append) == (tmp_path / "scene" / "frugalnerf_cache").resolve()
    assert cache.scene_cache_dir(tmp_path / "scene" / "transforms.json", said.append) == (
        tmp_path / "scene" / "frugalnerf_cache").resolve()
    assert said == []


def test_a_read_only_scene_caches_in_the_users_folder_said_once(tmp_path, monkeypatch):
    said = []
    scene = tmp_path / "shared" / "scene"
    scene.mkdir(parents=True)
    scene.chmod(0o555)
    try:
        monkeypatch.setenv("XDG_CACHE_HOME", str(tmp_path / "xdg"))
        first = cache.scene_cache_dir(scene, said.append)
        assert first.parent == tmp_path / "xdg" / "frugalnerf" and first.name.startswith("scene-")
        assert cache.scene_cache_dir(scene, said.append) == first and len(said) == 1 and str(first) in said[0]
        assert not (scene / "frugalnerf_cache").exists()
    finally:
        scene.chmod(0o755)


def test_without_a_home_folder_the_users_cache_is_in_the_temporary_folder(tmp_path, monkeypatch):
    def no_home():
        raise RuntimeError("Could not determine home directory.")

    monkeypatch.delenv("XDG_CACHE_HOME", raising=False)
    monkeypatch.setattr(Path, "home", staticmethod(no_home))
    monkeypatch.setattr(cache.tempfile, "gettempdir", lambda: str(tmp_path))
    assert cache.user_cache_root() == tmp_path / "frugalnerf"
