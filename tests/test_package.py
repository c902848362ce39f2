"""``import twinrl``: sub-packages as attributes, imported lazily."""

import subprocess
import sys


def test_subpackages_are_attributes_imported_on_first_use():
    code = ("import sys, twinrl\n"
            "assert 'twinrl.learn' not in sys.modules and 'twinrl.envs' not in sys.modules\n"
            "assert {'envs', 'physics', 'learn', 'real'} <= set(dir(twinrl))\n"
            "assert callable(twinrl.envs.make) and twinrl.physics.Sim and twinrl.real2sim\n"
            "assert 'twinrl.envs' in sys.modules and 'twinrl.learn' not in sys.modules\n"
            "assert twinrl.learn.__name__ == 'twinrl.learn' and twinrl.report.print_table\n"
            "try:\n"
            "    twinrl.nosuch\n"
            "except AttributeError as e:\n"
            "    assert \"no attribute 'nosuch'\" in str(e)\n"
            "else:\n"
            "    raise SystemExit('twinrl.nosuch did not raise')\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         timeout=120)
    assert out.returncode == 0, out.stderr[-3000:]
