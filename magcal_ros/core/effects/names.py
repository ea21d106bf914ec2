# Copyright 2026 The magcal_ros authors
#
# Licensed under the Apache License, Version 2.0 (the "License");
# you may not use this file except in compliance with the License.
# You may obtain a copy of the License at
#
#     http://www.apache.org/licenses/LICENSE-2.0
#
# Unless required by applicable law or agreed to in writing, software
# distributed under the License is distributed on an "AS IS" BASIS,
# WITHOUT WARRANTIES OR CONDITIONS OF ANY KIND, either express or implied.
# See the License for the specific language governing permissions and
# limitations under the License.
"""
A registry of classes by name: the one mechanism of the named effects, couplings and drivers.

:mod:`.registry`, :mod:`.couplings` and :mod:`.drivers` each hold one; their ``register_*``,
``unregister_*``, ``*_class`` and ``registered_*`` functions are its methods.
"""


class Registry:
    """
    Classes registered under a name: the built-in ones, then plug-ins (docs/plugins.md).

    Every class subclasses ``base``; messages call one ``what`` ('effect', 'coupling',
    'driver') and name the base ``base_name`` (where users import it from).
    """

    def __init__(self, base, what, base_name):
        self.base, self.what, self.base_name = base, what, base_name
        self.builtin = ()
        self._classes = {}

    def register(self, cls, name=None):
        """Register a subclass of the base under ``name`` (default ``cls.name``); return it."""
        if not (isinstance(cls, type) and issubclass(cls, self.base)):
            raise TypeError(f'{cls!r} is not a subclass of {self.base_name}')
        key = name or cls.name
        if key in self._classes and self._classes[key] is not cls:
            article = 'an' if self.what[0] in 'aeiou' else 'a'
            raise ValueError(f'{article} {self.what} named {key!r} is already registered '
                             f'({self._classes[key]!r})')
        self._classes[key] = cls
        return cls

    def unregister(self, name):
        """Remove the plug-in registered under ``name`` (tests, interactive sessions)."""
        if name in self.builtin:
            raise ValueError(f'{name!r} is a built-in {self.what} and cannot be unregistered')
        self._classes.pop(name, None)

    def get(self, name):
        """Return the class registered under ``name``, or None."""
        return self._classes.get(name)

    def names(self):
        """Return the registered names, sorted."""
        return sorted(self._classes)

    def seal_builtin(self):
        """Mark every class registered so far as built-in (never unregistered); return names."""
        self.builtin = tuple(self._classes)
        return self.builtin
