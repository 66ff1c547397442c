"""The components' nodes (one module each, ``node`` in it).

- ``predictors``: component 'predictors'
- ``monitor``: component 'monitor'
- ``analysis``: component 'analysis'
- ``plan``: component 'plan'
- ``legitimate``: component 'legitimate'
- ``execute``: component 'execute'
"""
