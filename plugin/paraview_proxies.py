"""ParaView proxies for the plugin's filters (the six and the Fibre Generator), generated from
their ``PROPERTIES``/``INPUTS``/``OUTPUTS`` tables (DESIGN §2: one definition of each property).

For each filter class this module defines a subclass with one ``Set<Name>`` method per property,
decorated with the Server Manager XML ParaView needs (type, default, range or enumeration,
tooltip), the input ports, named output ports, panel groups, the time-steps information property
and the "Muscle MSS" menu category, then registers it with ``smproxy.filter``. The proxy ``name``
(the state-file type) is the class name, e.g. ``FibreResampler``; the ``label`` gives the
``paraview.simple`` constructor, e.g. ``FibreResampler()`` from "Fibre Resampler".

The plugin, not the filters, is ParaView's entry point: each subclass's ``RequestData`` first
compiles the numeric kernels when this Python has not yet, saying so among the output messages
(:func:`~muscle_mss.app.warm_up.ensure_compiled`).

Only ParaView imports this module (through ``paraview_plugins/muscle_mss_plugin.py``).
"""
import contextlib
import importlib
import os
import sys
from xml.sax.saxutils import escape, quoteattr

from paraview.util.vtkAlgorithm import smhint, smproperty, smproxy

from muscle_mss.filters import EXPORTS, PLUGIN_FILTERS
from muscle_mss.app.warm_up import ensure_compiled, output_window_notice
from muscle_mss.filters.frame_cache import chosen_folder

# ParaView's readers are vtkFileSeriesReader objects; until the module wrapping that class is
# imported, Python sees one as its nearest wrapped base class, without GetNumberOfFileNames, and
# `paraview --state=…` imports none before the filters run: the solver's frame cache and the
# missing-file message read the readers' file names through it.
with contextlib.suppress(ImportError):
    from paraview.modules import vtkPVVTKExtensionsIOCore  # noqa: F401

MENU_CATEGORY = "Muscle MSS"

__all__ = list(PLUGIN_FILTERS)


def _documentation(text: str) -> str:
    return f"<Documentation>{escape(text)}</Documentation>"


def property_xml(prop) -> str:
    """The Server Manager XML of one :class:`~muscle_mss.core.properties.Property`."""
    if prop.kind == "string":
        return (f'<StringVectorProperty name="{prop.name}" command="Set{prop.name}" '
                f'number_of_elements="1" default_values={quoteattr(prop.default)}>'
                f'{_documentation(prop.doc)}</StringVectorProperty>')
    xml_type = "DoubleVectorProperty" if prop.kind == "double" else "IntVectorProperty"
    default = prop.stored_default
    default_text = repr(float(default)) if prop.kind == "double" else str(int(default))
    if prop.kind == "enum":
        entries = "".join(f'<Entry value="{i}" text={quoteattr(c)}/>'
                          for i, c in enumerate(prop.choices))
        domain = f'<EnumerationDomain name="enum">{entries}</EnumerationDomain>'
    elif prop.kind == "bool":
        domain = '<BooleanDomain name="bool"/>'
    else:
        tag = "DoubleRangeDomain" if prop.kind == "double" else "IntRangeDomain"
        bounds = "".join(f' {k}="{v}"' for k, v in (("min", prop.minimum), ("max", prop.maximum))
                         if v is not None)
        domain = f'<{tag} name="range"{bounds}/>'
    return (f'<{xml_type} name="{prop.name}" command="Set{prop.name}" number_of_elements="1" '
            f'default_values="{default_text}">{domain}{_documentation(prop.doc)}</{xml_type}>')


def input_xml(index: int, port) -> str:
    """The Server Manager XML of one input port."""
    hints = "<Hints><Optional/></Hints>" if port.optional else ""
    return (f'<InputProperty name="{port.name}" port_index="{index}" command="SetInputConnection">'
            f'<DataTypeDomain name="input_type"><DataType value="{port.data_type}"/>'
            f'</DataTypeDomain>{_documentation(port.doc)}{hints}</InputProperty>')


def groups_xml(properties) -> str:
    """``<PropertyGroup>`` elements for the properties' panel groups, in table order."""
    groups = {}
    for prop in properties:
        if prop.group:
            groups.setdefault(prop.group, []).append(prop.name)
    return "".join(f"<PropertyGroup label={quoteattr(label)}>"
                   + "".join(f'<Property name="{n}"/>' for n in names) + "</PropertyGroup>"
                   for label, names in groups.items())


def _setter(filter_class, prop):
    base_setter = getattr(filter_class, "Set" + prop.name)

    def setter(self, value):
        base_setter(self, value)
    setter.__name__ = "Set" + prop.name
    setter.__doc__ = prop.doc
    return setter


def threads_beside_paraview() -> None:
    """Run the kernels' threads on Numba's ``workqueue`` layer, unless
    ``NUMBA_THREADING_LAYER`` chooses one: ParaView has loaded its own OpenMP runtime, and
    Numba's ``omp`` layer (the one Debian's Numba picks) then ran 5-6 times slower (the MVC
    Surface Deformer's update of the demo thigh in pvpython: 2.1 s against 0.39 s, 2 cores).
    Called when the plugin loads (Numba, if not imported yet, reads the environment variable
    this sets when it is) and before each update; takes effect before the first parallel
    kernel runs, later calls change nothing."""
    if os.environ.get("NUMBA_THREADING_LAYER", "workqueue") != "workqueue":
        return
    os.environ["NUMBA_THREADING_LAYER"] = "workqueue"
    numba = sys.modules.get("numba")
    if numba is not None:
        numba.config.THREADING_LAYER = "workqueue"


threads_beside_paraview()


def make_proxy(filter_class):
    """The decorated ParaView proxy class for one filter class."""
    namespace = {"__module__": __name__, "__qualname__": filter_class.__name__,
                 "__doc__": filter_class.HELP}
    for prop in filter_class.PROPERTIES:
        namespace["Set" + prop.name] = smproperty.xml(property_xml(prop))(
            _setter(filter_class, prop))

    def request_data(self, request, in_info, out_info):
        # The plugin is ParaView's entry point: a first update in a Python whose kernels are
        # not compiled says so among the output messages, then compiles them all.
        threads_beside_paraview()
        ensure_compiled(output_window_notice)
        return filter_class.RequestData(self, request, in_info, out_info)
    namespace["RequestData"] = request_data
    if hasattr(filter_class, "default_frame_cache"):
        # in ParaView an empty frame cache property is the user's frame cache (muscle-mss run's default)
        namespace["default_frame_cache"] = staticmethod(lambda: chosen_folder(None))

    def timestep_values(self):
        # Never called: vtkSITimeStepsProperty reads TIME_STEPS of output port 0, so that the
        # time keeper (time slider, animation) sees the motion's times.
        return None
    namespace["GetTimestepValues"] = smproperty.doublevector(
        name="TimestepValues", information_only="1", si_class="vtkSITimeStepsProperty")(
        timestep_values)

    groups = groups_xml(filter_class.PROPERTIES)
    if groups:
        def panel_groups(self):
            # Carries the <PropertyGroup> XML, which must follow the properties: 5.11/5.12
            # sort properties by method name, and "zz_" sorts after every "Set…".
            return None
        namespace["zz_panel_groups"] = smproperty.xml(groups)(panel_groups)
    proxy = type(filter_class.__name__, (filter_class,), namespace)

    # Class-level XML: documentation, input ports, output port names, menu. (The decorators
    # are applied here in code, so their order is the order of these calls.)
    short = filter_class.HELP.split(". ")[0].rstrip(".") + "."
    class_xml = [f"<Documentation short_help={quoteattr(short)} "
                 f"long_help={quoteattr(short)}>{escape(filter_class.HELP)}</Documentation>"]
    class_xml += [input_xml(i, port) for i, port in enumerate(filter_class.INPUTS)]
    class_xml += [f'<OutputPort name="{port.name}" index="{i}"/>'
                  for i, port in enumerate(filter_class.OUTPUTS)]
    for xml in class_xml:
        proxy = smproperty.xml(xml)(proxy)
    proxy = smhint.xml(f'<ShowInMenu category="{MENU_CATEGORY}"/>')(proxy)
    return smproxy.filter(name=filter_class.__name__, label=filter_class.LABEL,
                          support_reload=False)(proxy)


for _name in PLUGIN_FILTERS:
    _module = importlib.import_module(f"muscle_mss.filters.{EXPORTS[_name]}")
    globals()[_name] = make_proxy(getattr(_module, _name))
