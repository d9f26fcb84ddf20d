// The model-step loop of the fused rollout (run_steps in fused.py) in C++: the same ATen calls
// in the same order on the same tensors, so the results are bit-identical to the Python loop;
// only the ~0.4 us of Python per call is gone (~1075 calls per plan at N = 50, H = 5).
// Built at setup by native_loop.py (python -m peel_planner_node.native_loop), never while
// planning. The workspace's tensors arrive by name (the field names of Shared, Step, Cell in
// fused_workspace.py and of Weights in fused_weights.py), are looked up once here, and run()
// releases the GIL, so rollout workers still run in parallel.
#include <torch/extension.h>

#include <optional>
#include <string>
#include <unordered_map>
#include <utility>
#include <vector>

namespace {

using Named = std::unordered_map<std::string, at::Tensor>;

at::Tensor take(const Named& m, const char* name) {
  auto it = m.find(name);
  TORCH_CHECK(it != m.end(), "rollout loop: no tensor named '", name, "'");
  return it->second;
}

std::optional<at::Tensor> maybe(const Named& m, const char* name) {
  auto it = m.find(name);
  if (it == m.end()) return std::nullopt;
  return it->second;
}

// One LSTM cell update (Eq. 11-16), gate-major [4, rows, hid], gates i, f, o, 2g (Cell).
struct Cell {
  std::optional<at::Tensor> x_proj;
  at::Tensor h_prev, gates, sig, c, sig_i, sig_f, sig_g, tanh_c, sig_o, h_out;
  explicit Cell(const Named& m)
      : x_proj(maybe(m, "x_proj")), h_prev(take(m, "h_prev")), gates(take(m, "gates")),
        sig(take(m, "sig")), c(take(m, "c")), sig_i(take(m, "sig_i")), sig_f(take(m, "sig_f")),
        sig_g(take(m, "sig_g")), tanh_c(take(m, "tanh_c")), sig_o(take(m, "sig_o")),
        h_out(take(m, "h_out")) {}
};

// Model step k (Step).
struct Step {
  at::Tensor window, h_prev, gates, gates_interior, fc1_v_bias, force_prev, force_next;
  std::optional<at::Tensor> edge_proj, gates_edge, h_last_window;
  std::vector<Cell> cells;
  Step(const Named& m, const std::vector<Named>& cell_maps)
      : window(take(m, "window")), h_prev(take(m, "h_prev")), gates(take(m, "gates")),
        gates_interior(take(m, "gates_interior")), fc1_v_bias(take(m, "fc1_v_bias")),
        force_prev(take(m, "force_prev")), force_next(take(m, "force_next")),
        edge_proj(maybe(m, "edge_proj")), gates_edge(maybe(m, "gates_edge")),
        h_last_window(maybe(m, "h_last_window")) {
    TORCH_CHECK(edge_proj.has_value() == gates_edge.has_value(),
                "rollout loop: edge_proj and gates_edge go together");
    for (const auto& c : cell_maps) cells.emplace_back(c);
  }
};

// A hidden FC layer of the regressor on [y, 1]: out = act @ weight after relu_(act).
struct Layer {
  at::Tensor act, weight, out;
  explicit Layer(const Named& m) : act(take(m, "act")), weight(take(m, "weight")),
                                   out(take(m, "out")) {}
};

class RolloutLoop {
 public:
  // shared: the buffers of Shared and the tensors of Weights the loop reads, by field name,
  // plus fc1_out, head_in, head_weight; layers: the hidden FC layers; steps[k] and cells[k]:
  // the fields of Step k and of its cells.
  RolloutLoop(const Named& shared, const std::vector<Named>& layers,
              const std::vector<Named>& steps, const std::vector<std::vector<Named>>& cells,
              bool att_shift)
      : conv_(take(shared, "conv")), conv_rows_(take(shared, "conv_rows")),
        conv_by_sample_(take(shared, "conv_by_sample")),
        att_hidden_(take(shared, "att_hidden")), att_logits_(take(shared, "att_logits")),
        att_sum_(take(shared, "att_sum")), scale_weights_(take(shared, "scale_weights")),
        scale_weights_by_sample_(take(shared, "scale_weights_by_sample")),
        weighted_s_(take(shared, "weighted_s")), lstm_input_x4_(take(shared, "lstm_input_x4")),
        x_proj_(take(shared, "x_proj")), x_proj_interior_(take(shared, "x_proj_interior")),
        h_last_(take(shared, "h_last")), conv_wave_(take(shared, "conv_wave")),
        conv_wave_bias_(take(shared, "conv_wave_bias")),
        att1_weight_t_(take(shared, "att1_weight_t")), att1_bias_(take(shared, "att1_bias")),
        att2_weight_t_(take(shared, "att2_weight_t")), att2_bias_(take(shared, "att2_bias")),
        scale_expand_(take(shared, "scale_expand")), wx_gates_aug_(take(shared, "wx_gates_aug")),
        wh_gates_(take(shared, "wh_gates")), fc1_h_t_(take(shared, "fc1_h_t")),
        fc1_out_(take(shared, "fc1_out")), head_in_(take(shared, "head_in")),
        head_weight_(take(shared, "head_weight")), att_shift_(att_shift) {
    TORCH_CHECK(steps.size() == cells.size(), "rollout loop: steps and cells differ in length");
    for (const auto& l : layers) layers_.emplace_back(l);
    for (size_t k = 0; k < steps.size(); ++k) steps_.emplace_back(steps[k], cells[k]);
  }

  void run() {
    for (auto& s : steps_) {
      // conv (Eq. 7) + scale attention (Eq. 8-10) + W_x x + b, as run_steps in fused.py
      at::addmm_out(conv_, conv_wave_bias_, s.window, conv_wave_);
      conv_.relu_();
      at::addmm_out(att_hidden_, att1_bias_, conv_rows_, att1_weight_t_);
      att_hidden_.sigmoid_();  // tanh, with the weights rearranged
      at::addmm_out(att_logits_, att2_bias_, att_hidden_, att2_weight_t_);
      if (att_shift_) {
        att_logits_.sub_(at::amax(att_logits_, {-1}, true));
      }
      att_logits_.exp_();
      at::sum_out(att_sum_, att_logits_, {-1}, true);
      att_logits_.div_(att_sum_);
      at::mm_out(scale_weights_, att_logits_, scale_expand_);
      at::mul_out(weighted_s_, conv_by_sample_, scale_weights_by_sample_);
      at::bmm_out(x_proj_, lstm_input_x4_, wx_gates_aug_);
      // W_h h of the in-flight windows + the shared interior and the top-edge projections
      at::bmm_out(s.gates, s.h_prev, wh_gates_);
      s.gates_interior.add_(x_proj_interior_);
      if (s.edge_proj.has_value()) {
        s.gates_edge->add_(*s.edge_proj);
      }
      // LSTM cell updates (Eq. 11-16), gate-major [4, m, hid], gates i, f, o, 2g
      for (auto& cl : s.cells) {
        if (cl.x_proj.has_value()) {
          at::baddbmm_out(cl.gates, *cl.x_proj, cl.h_prev, wh_gates_);
        }
        // tanh(x) = 2 sigmoid(2x) - 1 (lstm_pointwise in fused.py)
        at::sigmoid_out(cl.sig, cl.gates);
        cl.c.mul_(cl.sig_f).addcmul_(cl.sig_i, cl.sig_g, 2.0).sub_(cl.sig_i);
        at::add_out(cl.tanh_c, cl.c, cl.c);
        cl.tanh_c.sigmoid_();
        at::mul_out(cl.h_out, cl.sig_o, cl.tanh_c);
        cl.h_out.add_(cl.h_out).sub_(cl.sig_o);
      }
      if (s.h_last_window.has_value()) {
        h_last_.copy_(*s.h_last_window);
      }
      // regressor (3.1.3): F_{k+1} = F_k + FC layers([h_L, v_{k+1}])
      at::addmm_out(fc1_out_, s.fc1_v_bias, h_last_, fc1_h_t_);
      for (auto& l : layers_) {
        l.act.relu_();
        at::mm_out(l.out, l.act, l.weight);
      }
      head_in_.relu_();
      at::addmm_out(s.force_next, s.force_prev, head_in_, head_weight_);
    }
  }

 private:
  at::Tensor conv_, conv_rows_, conv_by_sample_, att_hidden_, att_logits_, att_sum_,
      scale_weights_, scale_weights_by_sample_, weighted_s_, lstm_input_x4_, x_proj_,
      x_proj_interior_, h_last_, conv_wave_, conv_wave_bias_, att1_weight_t_, att1_bias_,
      att2_weight_t_, att2_bias_, scale_expand_, wx_gates_aug_, wh_gates_, fc1_h_t_, fc1_out_,
      head_in_, head_weight_;
  bool att_shift_;
  std::vector<Layer> layers_;
  std::vector<Step> steps_;
};

}  // namespace

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  pybind11::class_<RolloutLoop>(m, "RolloutLoop")
      .def(pybind11::init<const Named&, const std::vector<Named>&, const std::vector<Named>&,
                          const std::vector<std::vector<Named>>&, bool>())
      .def("run", &RolloutLoop::run, pybind11::call_guard<pybind11::gil_scoped_release>());
}
