"""``cobel serve``: a local results dashboard (NiceGUI, ``pip install 'cobelrun[web]'``).

:mod:`cobelrun.web.data` finds and reads run and sweep folders through the validated readers;
:mod:`cobelrun.web.app` is the page over it. Importing this package imports neither NiceGUI nor
matplotlib.
"""
