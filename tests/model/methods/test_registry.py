"""model.methods.registry.inference_cost: one size per model, the size of the form that runs."""

from __future__ import annotations

import torch

from model.methods.registry import build_method, flops_per_pixel, inference_cost


def test_the_cost_of_wskpn_is_its_fused_form_and_the_method_is_left_as_it_was():
    method = build_method("wskpn:xs")
    before = {name: value.clone() for name, value in method.state_dict().items()}
    params, flops = inference_cost(method)
    assert method.training and method.state_dict().keys() == before.keys()
    assert all(torch.equal(value, before[name]) for name, value in method.state_dict().items())
    fused = build_method("wskpn:xs").for_inference()
    assert params == fused.parameter_count() < method.parameter_count()  # RepVGG branches fused away
    assert flops == flops_per_pixel(fused) < flops_per_pixel(method.eval())


def test_methods_without_an_inference_form_cost_what_they_are():
    for name, scale in (("munet:xs", 2), ("svgf", 1)):
        method = build_method(name, scale=scale)
        assert inference_cost(method) == (method.parameter_count(), flops_per_pixel(method))
