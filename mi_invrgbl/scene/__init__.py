"""What a scene is, below the applications: files, frames, poses, loading.

* :mod:`.frames`   -- ``frames.json`` records (read, check, write).
* :mod:`.posing`   -- the one function that moves objects, lights and
  sensors of a loaded scene per frame (:func:`.posing.place`).
* :mod:`.loading`  -- ``load_scene`` (``mi.load_file`` with one clear error).
* :mod:`.xml`      -- the one scene-XML builder and editor (``SceneDoc``,
  element makers, the nodes of this package's plugins).
* :mod:`.imported` -- the XML of an imported scene (``import``'s ``scene.xml``).

Import, fit, evaluation, the applications and the synthetic-street
generator all build on this package; it imports nothing above it.
"""
